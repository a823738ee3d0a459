"""The holes hostile testing found (issue 13), at small counts: the scenarios
of ground_station.faults.hostile_holes against the real controller, RobotNode
on a python-can virtual bus with the pymunk plant, the MAVLink node with
pymavlink's codec and signing, and the FTP server on a real storage root.
`qnav bench faults` runs the same with large counts."""

import pytest

from ground_station.faults import hostile_holes  # noqa: F401  (registers the scenarios)
from ground_station.faults.common import SCENARIOS

NAMES = ["can_future_tick", "can_forged_tick_pace", "can_encoder_jump", "can_frozen_sensor", "mav_failsafe_garbage",
         "mav_signing_bounds", "mav_signing_process", "ftp_sessions_quota"]


@pytest.mark.parametrize("name", NAMES)
def test_hostile_hole_stays_closed(name):
    sc = SCENARIOS[name]
    res = sc.run(sc.small, seed=1)
    assert res.tried == sc.small
    assert res.lost == 0, res.failures
