"""CAN faults at small counts (issue 9): the scenarios of
ground_station.faults.can_faults against the real controller, RobotNode,
python-can virtual bus and pymunk plant. `qnav bench faults` runs the same
with large counts."""

import pytest

from ground_station.faults import can_faults
from ground_station.faults.common import SCENARIOS

NAMES = ["can_sensor_stop", "can_driver_fault", "can_driver_watchdog", "can_estop", "can_counters"]


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
