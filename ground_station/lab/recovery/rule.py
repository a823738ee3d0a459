"""The hand-written recovery rules (`recoveries.PlannedTarget` without a table) as a table over
`decide`'s state: the baseline on the same state and events, and the learner's starting point.

Waiting: re-plan once the wait reaches r x 2 s in round r (wait_us = 2 s, at most max_rounds = 3 x);
on the waited-time bins (1, 2, 4, 6 s) that is bin >= 2, 3, 4 for rounds 0, 1, 2+. No route this
round: "no route" when this round makes the third still round (a still round: not moving, nothing
came up) or in the 6+ rounds bin (the rule's cap is 9 rounds: the table's bins say 6+); give way
when something came up to the robot; else another round."""

from __future__ import annotations

import numpy as np

from firmware_py.kinds.sector import decide


def rule_table() -> np.ndarray:
    """(N_STATES, N_ACTIONS) float: 1 for the rule's action, 0 elsewhere, -1 for invalid actions."""
    q = np.full((decide.N_STATES, decide.N_ACTIONS), -1.0)
    for s in range(decide.N_STATES):
        for a in decide.VALID[decide.event_of(s)]:
            q[s, a] = 0.0
    nb = len(decide.WAITED_S) + 1
    for w in range(nb):
        for r in range(4):
            for near in range(3):
                for moving in range(2):
                    s = ((w * 4 + r) * 3 + near) * 2 + moving
                    q[s, decide.REPLAN if w >= 2 + min(r, 2) else decide.WAIT] = 1.0
    for still in range(3):
        for rb, rounds in enumerate((1, 2, 3, 6)):
            for came_up in (False, True):
                for moving in (False, True):
                    for refuge in (False, True):
                        s = decide.round_state(still, rounds, came_up, moving, refuge)
                        after = still + (not moving and not came_up)
                        if after >= 3 or rb == 3:
                            a = decide.NO_ROUTE
                        elif came_up:
                            a = decide.GIVE_WAY
                        else:
                            a = decide.WAIT
                        q[s, a] = 1.0
    return q
