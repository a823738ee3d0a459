"""A remembered point in a blind gap does not hold the robot for good (the demo's 1-in-8 stall),
reproduced on the lockstep rig: the shipped sector policy with its local planner drives paper10's
items 23-25 of `qnav demo --policy policies:sector --obstacles 3 --movers 2` (east along the bottom
row, north up the one-cell corridor in column 7, east along row 7 to D) while the demo's second
mover walks to and fro at the corridor's exit.

With the movers started 24 or 79 periods on, the robot saw the mover a metre off (the reading's end
point placed on the front cone's middle ray), went round it (the point pinned while it did) and
drove up to the point, which stayed 8 degrees outside the front cone: no reading saw through it.
180 mm short of item 24, the collision monitor held every step into it and the robot wiggled in
place until the stall watch held it ('stalled: blocked ahead'), the mover long gone. Now the
memory clears a point where no body of `MIN_BODY_RADIUS_MM` could stand unseen, and the robot goes
on (firmware_py/kinds/sector/memory.py)."""

from __future__ import annotations

import pytest

from firmware_py.policy import load_policy
from firmware_py.shipped_policies import shipped_policy
from firmware_py.vehicle import CtrlState
from ground_station.lab.rigs.lockstep import LockstepRig
from ground_station.maps import load_map
from sim_bridge.obstacles import ObstacleLayer

START = (3.106, 0.242, 0.09)  # where the demo's robot began item 23 (paper10 cell (6, 9), facing east)
MISSION = [(3750, 250), (3750, 1250), (4750, 1250)]  # the demo's items 23, 24 (cell (7, 7)) and 25 (D)
# the demo's two movers (scenario seed 0) as they stood when the robot began item 23 (x, y, vx, vy, r, yields)
MOVERS = [[1821.0, 978.0, 306.0, 297.0, 150.0, 1.0], [3671.0, 1335.0, 163.0, 511.0, 150.0, 1.0]]


@pytest.mark.parametrize("offset", [24, 79])  # mover phases that stalled the robot at item 24
def test_the_robot_passes_the_corridor_exit_a_mover_walked_away_from(offset):
    rig = LockstepRig(load_map("paper10").occ, load_policy(shipped_policy("sector")), START, MISSION)
    layer = ObstacleLayer(rig.plant.world, [], [list(m) for m in MOVERS])
    for _ in range(offset):
        layer.step()
    rig.plant.obstacles = layer
    with rig:
        while rig.plant.time_us < 40_000_000 and not rig.runner.done.is_set():
            rig.tick()
    causes = [tr.cause for tr in rig.ctrl.transitions]
    assert rig.runner.result == "reached", (rig.runner.result, causes[-4:])
    assert not any("stalled" in c for c in causes)
    assert rig.ctrl.state == CtrlState.HOLD and rig.plant.world.contact_events == 0
