"""Hostile MAVLink input at small counts (issue 9): random, mutated, unsigned,
badly signed and replayed frames, hostile FTP payloads and out-of-range params
into the robot's MAVLink node core with signing on, then once over UDP into a
running `qnav-robot`. `qnav bench faults` runs 100 000 frames into the core."""

from ground_station.lab.faults import hostile_mav


def test_hostile_frames_into_the_node_core():
    res = hostile_mav.hostile_core(3000, seed=5)
    assert res.tried == 3000
    assert res.lost == 0, res.failures
    fig = res.figures
    # the hostile classes really reached the robot and were refused and counted
    assert fig["dropped_unsigned"] > 0 and fig["dropped_badsig"] > 0 and fig["dropped_replay"] > 0
    assert fig["ftp_naks"] > 0 and fig["ftp_refusals"] > 0


def test_hostile_frames_over_udp_into_qnav_robot():
    res = hostile_mav.hostile_udp(1500, seed=6)
    assert res.lost == 0, res.failures
    assert res.figures["robot_signing_dropped"] > 0
