"""`qnav mission upload --plan --follow` across processes (ground_station/lab/rigs/hil_scenarios.py
`replan`): lockstep pymunk sim with an unmapped disc across the planned way from A to B on paper10,
the robot on the shipped sector policy over a python-can-remote hub, MAVLink on UDP loopback, the
ground station as the `qnav` commands an operator types. The policy stalls at the disc (that is
the point: it has no memory to go round it); the follower sees the disc in the robot's
OBSTACLE_DISTANCE, re-plans round it when the robot reports no progress, and the robot reaches B."""

from __future__ import annotations

import pytest

from ground_station.canhub import CanHub
from ground_station.lab.rigs import hil_scenarios as hs


@pytest.mark.timeout(240)
def test_follow_replans_round_an_unmapped_disc_and_reaches_the_target(tmp_path):
    with CanHub("hil-replan") as hub:
        r = hs.replan(hub.spec, tmp_path)
    assert all(s["exit"] == 0 for s in r["steps"].values()), r["steps"]
    out = r["follow_out"]
    assert r["follow_exit"] == 0, (out, r["robot_log_tail"])
    assert "re-plan 1: round" in out and "all 1 targets reached (1 re-plan)" in out, out
    assert r["bumper_contacts"] == 0
