"""CAN faults (issue 9), the holes hostile testing found (issue 13) and the robot-runtime findings
(issue 29), at small counts: the scenarios of ground_station.lab.faults.can_faults, .hostile_holes and
.runtime_holes against the real controller,
RobotNode on a python-can virtual bus with the pymunk plant, the MAVLink node with pymavlink's
codec and signing, and the FTP server on a real storage root. `qnav bench faults` runs the
same with large counts."""

import pytest

from ground_station.lab.faults import (
    can_faults,
    hostile_holes,  # noqa: F401  (registers the scenarios)
    runtime_holes,  # noqa: F401
)
from ground_station.lab.faults.common import SCENARIOS

NAMES = ["can_sensor_stop", "can_driver_fault", "can_driver_watchdog", "can_estop", "can_counters",
         # hostile holes
         "can_future_tick", "can_forged_tick_pace", "can_encoder_jump", "can_frozen_sensor", "mav_failsafe_garbage",
         "mav_signing_bounds", "mav_signing_process", "ftp_sessions_quota",
         # issue 29's runtime findings (runtime_holes)
         "mav_hold_ends_exploration", "activation_worst_case", "planner_worst_case", "param_save_full_disk",
         "goal_refusals"]


@pytest.mark.parametrize("name", NAMES)
def test_lockstep_can_fault(name):
    sc = SCENARIOS[name]
    res = sc.run(sc.small, seed=1)
    assert res.tried == sc.small
    assert res.lost == 0, res.failures


def test_garbage_at_5khz_keeps_every_tick_and_counts_every_frame():
    res = can_faults.garbage(1, seed=1, duration_s=3.0)
    assert res.lost == 0, (res.failures, res.figures)
    run = res.figures["runs"][0]
    assert run["garbage_sent"] > 10_000  # 5 kHz for 3 s, whatever the machine's load
    assert run["can_errors"] == run["garbage_sent"]


def test_garbage_frames_never_decode_as_ours():
    import random

    from firmware_py import can_protocol as cp

    rng = random.Random(3)
    for _ in range(20_000):
        f = can_faults.garbage_frame(rng)
        with pytest.raises(cp.ProtocolError):
            cp.decode(f)
