"""The recovery decisions as a table: what the robot does when its local route is
closed, read from an int8 Q-table a policy carries (`recovery_table` metadata) instead of the
hand-written rules of `recoveries.PlannedTarget`.

Two decision events, each a row of one table (`N_STATES` rows x `N_ACTIONS` columns):

* **waiting** (`EV_WAIT`): every `DECIDE_US` of a WAIT (stopped, the route closed by something
  seen): `WAIT` (stand another `DECIDE_US`) or `REPLAN` (search the whole map now). State: time
  waited (`WAITED_S` bins), rounds so far (0, 1, 2, 3+), the nearest remembered point (at the
  robot: within radius + `veto_mm`; within `MOVING_NEAR_MM`; farther or none), and whether the
  scene moved while it waited (more than `moving_points` new points near the robot).
* **no route this round** (`EV_ROUND`): the whole map's search found no route: `WAIT` (back off,
  clear the layer round the robot, wait: another round), `GIVE_WAY` (stand aside at the refuge the
  search found; without one, as `WAIT`) or `NO_ROUTE` (say so and hold). State: still rounds so
  far (0, 1, 2+), rounds in all (1, 2, 3-5, 6+), whether something came up to the robot, whether
  it was a moving scene (what moved closed the way: the map is open without it), whether a refuge
  exists.

A bound stays hand-written: at most 3 x `max_rounds` rounds (then "no route"), and a wait of at
most 3 x `max_rounds` x `wait_us` (then a whole-map search), so no table can hold the robot for
ever. Pure stdlib: the table is an `array('b')`; the greedy column among the event's valid ones,
ties to the lowest index (as `base.best_action`).
"""

from __future__ import annotations

import base64
from array import array
from dataclasses import dataclass
from typing import Any

META_KEY = "recovery_table"  # policy metadata: {"version": 1, "scale": float, "table": base64 int8 rows}
VERSION = 1
WAIT, REPLAN, GIVE_WAY, NO_ROUTE = range(4)
ACTION_NAMES = ("wait", "replan", "give_way", "no_route")
N_ACTIONS = 4
EV_WAIT, EV_ROUND = 0, 1
VALID = {EV_WAIT: (WAIT, REPLAN), EV_ROUND: (WAIT, GIVE_WAY, NO_ROUTE)}
DECIDE_US = 1_000_000  # a waiting robot decides once a second
WAITED_S = (1, 2, 4, 6)  # waited-time bin edges, s (5 bins)
MOVING_NEAR_MM = 700  # memory.MOVING_NEAR_MM: "near the robot"
N_WAIT = (len(WAITED_S) + 1) * 4 * 3 * 2  # 120
N_ROUND = 3 * 4 * 2 * 2 * 2  # 96
N_STATES = N_WAIT + N_ROUND


def wait_state(waited_us: int, all_rounds: int, near: int, moving: bool) -> int:
    """The waiting event's row: `near` 0 = at the robot, 1 = within MOVING_NEAR_MM, 2 = farther/none."""
    w = sum(waited_us >= s * 1_000_000 for s in WAITED_S)
    return ((w * 4 + min(all_rounds, 3)) * 3 + near) * 2 + int(moving)


def round_state(still_rounds: int, all_rounds: int, came_up: bool, moving: bool, refuge: bool) -> int:
    """The no-route event's row (`all_rounds` counts this one: >= 1)."""
    r = 0 if all_rounds <= 1 else 1 if all_rounds == 2 else 2 if all_rounds <= 5 else 3
    return N_WAIT + (((min(still_rounds, 2) * 4 + r) * 2 + int(came_up)) * 2 + int(moving)) * 2 + int(refuge)


def event_of(state: int) -> int:
    return EV_WAIT if state < N_WAIT else EV_ROUND


@dataclass(frozen=True)
class RecoveryTable:
    """An int8 table of `N_STATES` x `N_ACTIONS` (q ~= int x scale)."""

    table: array[int]  # typecode "b"
    scale: float = 1.0

    def choose(self, state: int) -> int:
        """The greedy action among the event's valid ones (ties to the lowest index)."""
        row = self.table[state * N_ACTIONS:(state + 1) * N_ACTIONS]
        valid = VALID[event_of(state)]
        return max(valid, key=lambda a: (row[a], -a))

    @classmethod
    def from_metadata(cls, meta: Any) -> RecoveryTable:
        """The table in a policy's metadata value; ValueError with one line naming what is wrong."""
        if not isinstance(meta, dict) or set(meta) != {"version", "scale", "table"}:
            raise ValueError(f"{META_KEY} is not an object of version, scale and table")
        if meta["version"] != VERSION:
            raise ValueError(f"{META_KEY}.version = {meta['version']!r} (this robot reads {VERSION})")
        scale = meta["scale"]
        if not isinstance(scale, (int, float)) or isinstance(scale, bool) or not 0 < scale < 1e9:
            raise ValueError(f"{META_KEY}.scale = {scale!r} is not a positive number")
        try:
            raw = base64.b64decode(str(meta["table"]), validate=True)
        except ValueError:
            raise ValueError(f"{META_KEY}.table is not base64") from None
        if len(raw) != N_STATES * N_ACTIONS:
            raise ValueError(f"{META_KEY}.table is {len(raw)} bytes, need {N_STATES * N_ACTIONS} "
                             f"({N_STATES} states x {N_ACTIONS} actions)")
        t = array("b", raw)
        if -128 in t:
            raise ValueError(f"{META_KEY}.table holds -128 (int8 values are symmetric, -127..127)")
        return cls(t, float(scale))

    def to_metadata(self) -> dict[str, Any]:
        return {"version": VERSION, "scale": self.scale, "table": base64.b64encode(self.table.tobytes()).decode()}


def recovery_table(metadata: dict[str, Any]) -> RecoveryTable | None:
    """The policy's recovery table, or None (the hand-written rules decide)."""
    return RecoveryTable.from_metadata(metadata[META_KEY]) if META_KEY in metadata else None
