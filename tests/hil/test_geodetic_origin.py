"""The robot's geodetic origin as a ground station on a world map meets it (issue 46
item 7; QGroundControl itself cannot run here, so pymavlink and MAVProxy stand in):

* a real `qnav-robot` over UDP sends GPS_GLOBAL_ORIGIN and HOME_POSITION unasked, equal
  to its ORIGIN_* parameters, as soon as a ground station appears and when the origin
  changes, and streams GLOBAL_POSITION_INT around it;
* on `qnav sitl`, a `qnav mission upload --targets` mission is listed by MAVProxy's
  `wp list` at the robot's origin (lat/lon, not 0/0 nor metres read as degrees), and a
  mission MAVProxy loads in global coordinates (origin + metres) is driven to completion.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from firmware_py import robot_spec
from firmware_py.mavlink import frames
from firmware_py.mavlink.params import as_float32
from ground_station.subprocs import free_udp_port, stop_process
from tests.hil.test_sitl import SitlProcess, child_env
from tests.support.consoles import MavProxy

BIN = Path(sys.executable).parent
# ArduPilot SITL's default home (CMAC, Canberra), the robot's origin in these tests
CMAC_LAT, CMAC_LON, CMAC_ALT_MM = -353632610, 1491652300, 584000
PROMPT_S = 1.0  # "at once": well inside the 5 s period of the origin stream


def _gcs(port: int):
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    return mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)


def _origin_and_home(conn, timeout_s: float) -> tuple[dict, float]:
    """GPS_GLOBAL_ORIGIN and HOME_POSITION (type -> message), heartbeats sent meanwhile, and how
    long after the robot's first frame the later of the two came."""
    got: dict = {}
    first = None
    next_beat = 0.0
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and len(got) < 2:
        if time.monotonic() >= next_beat:
            conn.mav.heartbeat_send(6, 8, 0, 0, 0)  # GCS, MAV_AUTOPILOT_INVALID
            next_beat = time.monotonic() + 0.5
        msg = conn.recv_match(blocking=True, timeout=0.05)
        if msg is None or msg.get_type() == "BAD_DATA" or msg.get_srcSystem() != 1:
            continue
        if first is None:
            first = time.monotonic()
        if msg.get_type() in ("GPS_GLOBAL_ORIGIN", "HOME_POSITION"):
            got.setdefault(msg.get_type(), msg)
    assert first is not None, "no frame from the robot"
    return got, time.monotonic() - first


def _param(conn, name: str) -> float:
    for _ in range(20):
        conn.mav.param_request_read_send(1, 1, name.encode(), -1)
        msg = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.5)
        if msg is not None and msg.param_id == name:
            return msg.param_value
    raise AssertionError(f"no PARAM_VALUE {name}")


@pytest.mark.timeout(120)
def test_a_robot_announces_its_origin_and_home_unasked_and_streams_its_global_position(tmp_path):
    storage, port = tmp_path / "robot", free_udp_port()
    (storage / "params").mkdir(parents=True)
    (storage / "params" / "params.json").write_text(json.dumps(
        {"version": 1, "params": {"ORIGIN_LAT": CMAC_LAT, "ORIGIN_LON": CMAC_LON, "ORIGIN_ALT_MM": CMAC_ALT_MM}}))
    robot = subprocess.Popen([BIN / "qnav-robot", "--can", f"virtual:origin-{port}", "--storage", storage,
                              "--mavlink", f"udpin:127.0.0.1:{port}", "-q"],
                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                             env=child_env())
    try:
        # a first ground station: both arrive unasked and carry the origin parameters
        gcs = _gcs(port)
        got, _ = _origin_and_home(gcs, 30)
        assert set(got) == {"GPS_GLOBAL_ORIGIN", "HOME_POSITION"}, got
        for msg in got.values():
            assert (msg.latitude, msg.longitude, msg.altitude) == (CMAC_LAT, CMAC_LON, CMAC_ALT_MM), msg
        for name, value in (("ORIGIN_LAT", CMAC_LAT), ("ORIGIN_LON", CMAC_LON), ("ORIGIN_ALT_MM", CMAC_ALT_MM)):
            assert _param(gcs, name) == as_float32(value)  # PARAM_VALUE: the float32 image of the stored value
        # GLOBAL_POSITION_INT streams (TELEM_POS_HZ, 5) around the origin at its altitude
        t_end, fixes = time.monotonic() + 1.5, []
        while time.monotonic() < t_end:
            msg = gcs.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=0.2)
            if msg is not None:
                fixes.append(msg)
        assert len(fixes) >= 5, len(fixes)
        for fix in fixes:
            x_mm, y_mm = frames.global_to_world(fix.lat, fix.lon, CMAC_LAT, CMAC_LON)
            assert math.hypot(x_mm, y_mm) < 100_000 and fix.alt == CMAC_ALT_MM, fix  # on the arena, not at 0/0
        # it goes quiet right after an origin; 2.5 s later another ground station appears (the period is 5 s)
        gcs.recv_match(type="GPS_GLOBAL_ORIGIN", blocking=True, timeout=10)
        gcs.close()
        time.sleep(2.5)
        gcs = _gcs(port)
        got, after_s = _origin_and_home(gcs, 6)
        assert set(got) == {"GPS_GLOBAL_ORIGIN", "HOME_POSITION"} and after_s < PROMPT_S, \
            f"a GCS that appeared waited {after_s:.1f} s for the robot's origin and home"
        # the origin moves (PARAM_SET, a float32-exact value): announced at once
        new_lat = -353664608  # 35.6 m south, a multiple of 32: exact in float32
        gcs.mav.param_set_send(1, 1, b"ORIGIN_LAT", float(new_lat), 6)  # MAV_PARAM_TYPE_INT32
        t0, seen = time.monotonic(), None
        while time.monotonic() - t0 < 6 and seen is None:
            msg = gcs.recv_match(type="GPS_GLOBAL_ORIGIN", blocking=True, timeout=0.2)
            if msg is not None and msg.latitude == new_lat:
                seen = time.monotonic() - t0
        assert seen is not None and seen < PROMPT_S, f"the new origin came after {seen} s"
        gcs.close()
    finally:
        stop_process(robot)


def _wp_list(mp: MavProxy, count: int) -> list[tuple[int, int, float, float]]:
    """MAVProxy's `wp list` lines: (command, frame, x, y) as it prints them."""
    pattern = r"(?:^|\s)(\d+) (\d+) (-?\d+\.\d{10}) (-?\d+\.\d{10}) "  # "%u %u %.10f %.10f %f p1=..."
    mp.send("wp list")
    mp.expect(rf"Requesting {count} waypoints", 30)  # this listing's rows follow
    rows: list[tuple[int, int, float, float]] = []
    while len(rows) < count:
        match = re.search(pattern, mp.expect(pattern, 30))
        assert match is not None
        cmd, frame, x, y = match.groups()
        rows.append((int(cmd), int(frame), float(x), float(y)))
    return rows


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_sitl_missions_in_global_coordinates_for_mavproxy_and_from_qnav(tmp_path):
    # lockstep at most x4 (docs/walkthrough.md's pace): load only slows the run (tests/hil/test_sitl.py)
    with SitlProcess(tmp_path, "--lockstep", "--speed", "4") as sitl:
        master = sitl.up()
        url = ["--mavlink", master, "--no-tlog"]

        def qnav(*argv: str) -> str:
            r = subprocess.run([sys.executable, "-m", "ground_station.cli", *argv, *url], capture_output=True,
                               text=True, env=child_env(), cwd=tmp_path, timeout=120)
            assert r.returncode == 0, (argv, r.stdout, r.stderr)
            return r.stdout

        # the robot's origin moved to ArduPilot's SITL home (float32-exact values: PARAM_SET carries a float)
        lat0, lon0 = -353632608, 1491652352
        qnav("param", "set", "ORIGIN_LAT", str(lat0))
        qnav("param", "set", "ORIGIN_LON", str(lon0))
        # (b) qnav's mission from map targets A (2,2) and D (9,7) of paper10 (0.5 m cells, 10 rows)
        targets = [robot_spec.cell_center_mm(2, 2, 10), robot_spec.cell_center_mm(9, 7, 10)]
        assert "mission of 2 waypoints accepted" in qnav("mission", "upload", "--targets", "A,D")
        mp = MavProxy(master, tmp_path, modules="param,wp,mode,arm,cmdlong")
        sitl.closing(mp.close)
        mp.expect(r"Detected vehicle 1:1", 30)
        rows = _wp_list(mp, 2)
        for (cmd, frame, lat, lon), want in zip(rows, targets, strict=True):
            assert cmd == 16 and frame == 3, rows  # NAV_WAYPOINT, MAV_FRAME_GLOBAL_RELATIVE_ALT
            got_mm = frames.global_to_world(round(lat * 1e7), round(lon * 1e7), lat0, lon0)
            assert math.dist(got_mm, want) < 10, (rows, want)  # at the robot's origin + the target's metres
        # (c) MAVProxy's own mission in global coordinates: the origin + metres, D then A
        lines = ["QGC WPL 110"]
        for seq, (x_mm, y_mm) in enumerate(reversed(targets)):
            lat, lon = frames.world_to_global(x_mm, y_mm, lat0, lon0)
            lines.append(f"{seq}\t0\t3\t16\t0\t0\t0\t0\t{lat / 1e7:.7f}\t{lon / 1e7:.7f}\t0\t1")
        (tmp_path / "cmac.txt").write_text("\n".join(lines) + "\n")
        mp.send(f"wp load {tmp_path / 'cmac.txt'}")
        mp.expect(r"MISSION_ACK: TYPE_MISSION: ACCEPTED", 30)  # the upload is over ("Loaded" comes before it)
        rows = _wp_list(mp, 2)  # listed back as loaded
        assert [(round(r[2] * 1e7), round(r[3] * 1e7)) for r in rows] == \
            [frames.world_to_global(*t, lat0, lon0) for t in reversed(targets)], rows
        mp.send("wp set 0")
        mp.send("arm throttle")
        mp.expect(r"COMPONENT_ARM_DISARM: ACCEPTED", 30)
        mp.send("mode AUTO")
        mp.expect(r"mission complete", 120)
    assert sitl.code == 0, "\n".join(sitl.log[-20:])
    with open(sitl.out / "trajectory.csv", newline="") as f:
        rows_csv = list(csv.DictReader(f))
    x, y = float(rows_csv[-1]["x_m"]), float(rows_csv[-1]["y_m"])
    assert math.hypot(x - targets[0][0] / 1000, y - targets[0][1] / 1000) < 0.2, (x, y)  # ground truth: at A
    assert not re.search(r"fence breach", "\n".join(mp.log))
