"""A stock ground station, MAVProxy, scripted non-interactively (commands on
its stdin, answers read from its stdout) against the robot's MAVLink node
over UDP loopback: it must detect the vehicle, name its mode, fetch every
parameter, set one, arm, and load a waypoint file."""

from __future__ import annotations

import time

import pytest

from firmware_py import robot_spec
from firmware_py.mavlink import frames
from firmware_py.mavlink.params import PARAMS
from ground_station.subprocs import free_udp_port
from tests.support.consoles import MavProxy
from tests.support.mav_vehicle import Robot


def wait_for(pred, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


@pytest.mark.slow
def test_mavproxy_sees_lists_sets_arms_and_loads_a_mission(tmp_path):
    port = free_udp_port()
    r = Robot(tmp_path / "storage", port)
    mp = MavProxy(f"udpin:127.0.0.1:{port}", tmp_path)
    try:
        mp.expect(r"Detected vehicle 1:1")
        mp.expect(rf"Received {len(PARAMS)} parameters", 30)
        mp.send("param show GOAL_TOL_MM")
        mp.expect(rf"GOAL_TOL_MM\s+{robot_spec.GOAL_TOLERANCE_MM}")
        mp.send("param set GOAL_TOL_MM 250")
        assert wait_for(lambda: r.node.params.get("GOAL_TOL_MM") == 250)
        mp.send("arm throttle")
        mp.expect(r"COMPONENT_ARM_DISARM: ACCEPTED")
        assert r.vehicle.st.armed
        # a waypoint file as MAVProxy/ArduPilot users write it: global frame around the origin
        lat0, lon0 = r.node.params.get("ORIGIN_LAT"), r.node.params.get("ORIGIN_LON")
        targets = [(1250, 3750), (4750, 4750)]
        lines = ["QGC WPL 110"]
        for i, (x, y) in enumerate(targets):
            lat, lon = frames.world_to_global(x, y, lat0, lon0)
            lines.append(f"{i}\t0\t3\t16\t0\t0\t0\t0\t{lat / 1e7:.7f}\t{lon / 1e7:.7f}\t0\t1")
        (tmp_path / "tour.txt").write_text("\n".join(lines) + "\n")
        mp.send(f"wp load {tmp_path / 'tour.txt'}")
        mp.expect(r"MISSION_ACK: TYPE_MISSION: ACCEPTED")
        assert len(r.vehicle.mission) == 2
        for got, want in zip(r.vehicle.mission, targets, strict=True):
            assert abs(got[0] - want[0]) <= 12 and abs(got[1] - want[1]) <= 12  # 1e-7 deg ~ 11 mm
        mp.send("mode GUIDED")
        mp.expect(r"DO_SET_MODE: ACCEPTED")
        mp.expect(r"^GUIDED>|Mode GUIDED", 5)
    finally:
        mp.close()
        r.stop()
