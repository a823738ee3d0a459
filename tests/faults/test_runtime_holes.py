"""Issue 29's robot-runtime findings as fault scenarios (ground_station.faults.runtime_holes), at
small counts: exploration ended by Hold / failsafe / disarm at the next tick, a worst-case policy
activated while driving, the planner's extreme metadata with obstacles (search off the tick), a
parameter save on a full disk, goals outside the map or in walls refused. `qnav bench faults` runs
the same with large counts."""

import pytest

from ground_station.faults import runtime_holes  # noqa: F401  (registers the scenarios)
from ground_station.faults.common import SCENARIOS

NAMES = ["mav_hold_ends_exploration", "activation_worst_case", "planner_worst_case", "param_save_full_disk",
         "goal_refusals"]


@pytest.mark.parametrize("name", NAMES)
def test_runtime_hole_stays_closed(name):
    sc = SCENARIOS[name]
    res = sc.run(sc.small, seed=1)
    assert res.tried == sc.small
    assert res.lost == 0, res.failures
