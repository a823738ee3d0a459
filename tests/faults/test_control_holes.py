"""Issue 43 findings 1 and 3 at small counts (ground_station.lab.faults.control_holes): another
system's sticks, RC overrides, mode + goal and PARAM_SET, and broadcast sticks, move no wheel
while the operator's own sticks do; a 1,500/s PARAM_REQUEST_LIST flood cannot delay Hold or
stretch the deadman, and the robot's PARAM_VALUEs stay within the stream's rate (the code
before answered 31 a request). `qnav bench faults` runs the same at large counts."""

import pytest

from firmware_py.mavlink.param_stream import RATE_HZ
from ground_station.lab.faults import control_holes


def test_only_the_operators_gcs_steers():
    res = control_holes.foreign_control(len(control_holes.ATTACKS), seed=0)
    assert res.tried == len(control_holes.ATTACKS)
    assert res.lost == 0, res.failures
    assert set(res.figures["non_zero_commands_by_attack"]) == set(control_holes.ATTACKS)
    assert sum(res.figures["non_zero_commands_by_attack"].values()) == 0


def test_param_list_flood_cannot_delay_hold_or_the_deadman():
    res = control_holes.param_list_flood(2, seed=0)  # one Hold, one deadman
    assert res.lost == 0, res.failures
    assert res.figures["param_values_per_s_max"] <= RATE_HZ
    assert res.figures["param_values_per_request"] < 1.0
    assert 0 < res.figures["deadman_stop_ms_max"] <= 550


@pytest.mark.wallclock  # paced HIL: the operator's ACK is judged on the wall clock
@pytest.mark.timeout(240)
def test_param_list_flood_on_real_processes_hold_acked_at_once():
    res = control_holes.param_list_flood_hil(1, seed=0)
    assert res.lost == 0, res.failures
    run = res.figures["runs"][0]
    assert run["flood_sent"] > 1000
    assert run["hold_after_robot_ms"] is not None and run["hold_after_robot_ms"] <= 500
