"""The MAVLink node over real UDP loopback: the robot shell (udpout, as a
robot talks to a ground station) against `qnav` commands and pymavlink
clients (udpin). The vehicle is tests/support/mav_vehicle.py; the full HIL run
with the controller and the pymunk sim is in the integration tests."""

from __future__ import annotations

import hashlib
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.support.mav_vehicle import Robot

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

from firmware_py import robot_spec  # noqa: E402
from ground_station import cli  # noqa: E402
from ground_station.mavlink.link import Link  # noqa: E402
from ground_station.subprocs import free_udp_port  # noqa: E402

m = mavutil.mavlink
VENV_BIN = Path(sys.executable).parent


@pytest.fixture
def rig(tmp_path):
    port = free_udp_port()
    robots = []

    def start(key_file: Path | None = None) -> Robot:
        r = Robot(tmp_path / "storage", port, key_file)
        robots.append(r)
        return r

    yield port, start, tmp_path
    for r in robots:
        r.stop()


def qnav(port: int, *argv: str, key: Path | None = None, tlog: Path | None = None,
         timeout: float = 5) -> tuple[int, str]:
    """Run a qnav command in-process; returns (exit code, stderr+stdout)."""
    import contextlib
    import io

    args = list(argv) + ["--mavlink", f"udpin:127.0.0.1:{port}", "--timeout", str(timeout)]
    args += ["--signing-key", str(key)] if key else []
    args += ["--tlog", str(tlog)] if tlog else ["--no-tlog"]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(args)
    return code, err.getvalue() + out.getvalue()


def test_commands_params_and_tlog_over_udp(rig):
    port, start, tmp = rig
    r = start()
    tlog = tmp / "arm.tlog"
    code, out = qnav(port, "arm", tlog=tlog)
    assert code == 0 and r.vehicle.st.armed, out
    # mavlogdump (pymavlink's own tool) reads our tlog, both directions
    dump = subprocess.run([sys.executable, str(VENV_BIN / "mavlogdump.py"), "--types", "COMMAND_LONG,COMMAND_ACK",
                           str(tlog)], capture_output=True, text=True, timeout=60)
    assert dump.returncode == 0, dump.stderr
    sent = [ln for ln in dump.stdout.splitlines() if "COMMAND_LONG" in ln and "command : 400" in ln]
    acks = [ln for ln in dump.stdout.splitlines() if "COMMAND_ACK" in ln and "command : 400" in ln]
    assert sent and acks and "result : 0" in acks[-1], dump.stdout

    code, out = qnav(port, "mode", "auto")
    assert code == 3 and "no mission" in out  # the robot's reason reaches the user
    assert qnav(port, "mode", "guided")[0] == 0 and r.vehicle.st.mode == 15
    code, out = qnav(port, "goal", "1.5", "2.0")
    assert code == 0 and r.vehicle.st.goal_mm in ((1500, 2000), None)  # may already be reached
    assert qnav(port, "disarm")[0] == 0 and not r.vehicle.st.armed

    code, out = qnav(port, "param", "set", "GOAL_TOL_MM", "200")
    assert code == 0 and out.split() == ["GOAL_TOL_MM", "200"]
    code, out = qnav(port, "param", "set", "GOAL_TOL_MM", "99999")
    assert code == 3 and "out of range" in out
    code, out = qnav(port, "param", "list")
    assert code == 0 and "SYSID_THISMAV" in out, out
    # the value, then the robot's own description and range from its parameter metadata over FTP
    line = next(x for x in out.splitlines() if x.startswith("GOAL_TOL_MM "))
    assert line.split()[1] == "200" and "goal counts as reached" in line and "[20..2000 mm]" in line, line
    code, out = qnav(port, "param", "list", "--no-descriptions")
    assert code == 0 and "goal counts as reached" not in out
    code, out = qnav(port, "param", "get", "NOPE")
    assert code == 3 and "unknown parameter NOPE" in out

    # reboot: params reloaded from storage, the refused value never stored
    with Link(f"udpin:127.0.0.1:{port}", tlog=False) as link:
        link.connect(5)
        link.command(m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
    assert r.node.reboots == 1
    assert qnav(port, "param", "get", "GOAL_TOL_MM")[1].split() == ["GOAL_TOL_MM", "200"]


def test_mission_targets_upload_download_and_auto_run(rig):
    port, start, tmp = rig
    r = start()
    code, out = qnav(port, "mission", "upload", "--targets", "A,B,C,D")  # no --map, and the robot has none
    assert code == 2 and "the robot has no /maps/active.map and its active policy carries no map: give --map" in out, out
    code, out = qnav(port, "mission", "upload", "--targets", "A,B,C,D", "--map", "paper10")
    assert code == 0 and "4 waypoints" in out, out
    # paper10 targets A (2,2) B (9,0) C (0,9) D (9,7), 0.5 m cells, 10 rows; sent as lat/lon around the
    # robot's origin (1e-7 deg steps: back within 6 mm)
    want = [robot_spec.cell_center_mm(c, row, 10) for c, row in ((2, 2), (9, 0), (0, 9), (9, 7))]
    assert len(r.vehicle.mission) == 4
    assert all(math.dist(got, w) < 7 for got, w in zip(r.vehicle.mission, want, strict=True)), r.vehicle.mission
    wpl = tmp / "down.waypoints"
    code, out = qnav(port, "mission", "download", "--out", str(wpl))
    assert code == 0 and "  0 global lat=" in out and "(frame 3)  x=1.25" in out and "m east  y=3.75" in out, out
    assert wpl.read_text().startswith("QGC WPL 110")
    # the file goes back up unchanged
    code, _ = qnav(port, "mission", "upload", str(wpl))
    assert code == 0 and math.dist(r.vehicle.mission[3], robot_spec.cell_center_mm(9, 7, 10)) < 7
    # --frame local: LOCAL_NED, exact
    code, out = qnav(port, "mission", "upload", "--targets", "A,B,C,D", "--map", "paper10", "--frame", "local")
    assert code == 0 and r.vehicle.mission == want, out
    code, out = qnav(port, "mission", "download")
    assert code == 0 and "x=1.250 m east  y=3.750 m north" in out and " global " not in out, out
    assert qnav(port, "mission", "upload", "--targets", "A,Z", "--map", "paper10")[0] == 2  # no target Z

    with Link(f"udpin:127.0.0.1:{port}", tlog=False) as link:
        link.connect(5)
        link.command(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        link.command(m.MAV_CMD_MISSION_START)
        reached = []
        deadline = time.monotonic() + 30
        while len(reached) < 4 and time.monotonic() < deadline:
            msg = link.recv("MISSION_ITEM_REACHED", 1.0)
            if msg is not None:
                reached.append(msg.seq)
        assert reached == [0, 1, 2, 3]
        cur = link.recv("MISSION_CURRENT", 3.0)
        assert cur is not None and cur.mission_state == m.MISSION_STATE_COMPLETE


def test_gcs_failsafe_within_timeout_plus_one_period(rig):
    port, start, _tmp = rig
    r = start()
    with Link(f"udpin:127.0.0.1:{port}", tlog=False) as link:
        link.connect(5)
        link.param_set("FS_GCS_TOUT_MS", 1000)
        link.command(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        link.command(m.MAV_CMD_DO_SET_MODE, 1, 15)
        for _ in range(3):
            link.send_heartbeat()
            time.sleep(0.2)
        assert not r.node.failsafe
        last_hb = r.node.gcs_last_heartbeat_us
        text = link.recv("STATUSTEXT", 5.0, cond=lambda t: t.text.startswith("GCS failsafe"))
        assert text is not None and text.severity == m.MAV_SEVERITY_CRITICAL
        delay = r.node.failsafe_since_us - last_hb
        assert 1_000_000 < delay <= 1_000_000 + robot_spec.CONTROL_PERIOD_US  # on the robot clock
        hb = link.recv("HEARTBEAT", 2.0)
        assert hb.custom_mode == 4 and hb.system_status == m.MAV_STATE_CRITICAL  # Hold
        link.send_heartbeat()
        assert link.recv("STATUSTEXT", 3.0, cond=lambda t: t.text == "GCS failsafe cleared") is not None
        assert not r.node.failsafe


def test_signing_over_udp_unsigned_ignored_signed_works_replay_dropped(rig):
    port, start, tmp = rig
    key_file = tmp / "robot.key"
    key_file.write_text(hashlib.sha256(b"field key").hexdigest() + "\n")
    r = start(key_file)
    # an unsigned ground station: its ARM is ignored and counted
    plain = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
    try:
        assert plain.recv_match(type="HEARTBEAT", blocking=True, timeout=5) is not None
        for _ in range(3):
            plain.mav.command_long_send(1, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        assert plain.recv_match(type="COMMAND_ACK", blocking=True, timeout=1.0) is None
    finally:
        plain.close()
    assert not r.vehicle.st.armed and r.node.signing.dropped_unsigned >= 3
    dropped_before = r.node.signing.dropped
    # a signed one works
    code, out = qnav(port, "arm", key=key_file)
    assert code == 0 and r.vehicle.st.armed, out
    with Link(f"udpin:127.0.0.1:{port}", signing_key=key_file, tlog=False) as link:
        link.connect(5)
        sent = []
        link.conn.mav.set_send_callback(lambda msg, *a, **k: sent.append(bytes(msg.get_msgbuf())))
        link.command(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        signed_arm = sent[-1]
        assert signed_arm[2] & 1  # incompat flag: signed
        link.command(m.MAV_CMD_COMPONENT_ARM_DISARM, 0)
        assert not r.vehicle.st.armed
        link.conn.write(signed_arm)  # replay the captured signed ARM
        time.sleep(0.5)
        assert not r.vehicle.st.armed and r.node.signing.dropped_replay >= 1
        # the drop counter is visible to the ground station in SYS_STATUS
        link.command(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_SYS_STATUS)
        st = link.recv("SYS_STATUS", 2.0)
        assert st is not None and st.errors_count3 > dropped_before
        # robot frames are signed
        hb = link.recv("HEARTBEAT", 2.0)
        assert hb.get_signed()


def test_source_ids_default_apart_from_qgc_and_mavproxy_and_can_be_set(rig):
    """Issue 29 finding 2: qnav sent as QGroundControl does (255/190), so the
    two collided on one robot. Now 255/25 by default, settable per command."""
    port, start, tmp = rig
    r = start()

    def sent_from(tlog: Path) -> set[tuple[int, int]]:
        log = mavutil.mavlink_connection(str(tlog))
        ids = set()
        while (msg := log.recv_match(type="COMMAND_LONG")) is not None:
            ids.add((msg.get_srcSystem(), msg.get_srcComponent()))
        return ids

    assert qnav(port, "arm", tlog=tmp / "default.tlog")[0] == 0 and r.vehicle.st.armed
    assert sent_from(tmp / "default.tlog") == {(255, 25)}
    # another system id is used as given; the robot takes control from SYSID_MYGCS (255) only (issue 43)
    code, out = qnav(port, "disarm", "--source-system", "254", "--source-component", "26", tlog=tmp / "set.tlog")
    assert code == 3 and "DENIED" in out and "SYSID_MYGCS" in out and r.vehicle.st.armed, out
    assert sent_from(tmp / "set.tlog") == {(254, 26)}
    code, out = qnav(port, "disarm", "--source-component", "26", tlog=tmp / "own.tlog")
    assert code == 0 and not r.vehicle.st.armed, out
    assert sent_from(tmp / "own.tlog") == {(255, 26)}
    for bad in (["--source-system", "0"], ["--source-component", "256"], ["--source-system", "x"]):
        with pytest.raises(SystemExit) as exc:
            qnav(port, "arm", *bad)
        assert exc.value.code == 2


def test_mission_targets_on_the_robots_own_map(rig):
    """Issue 30 item 4: the robot's active policy carries its map, so `--targets` needs no `--map`,
    and a `--map` that is not the robot's is refused in one line naming both (read over MAVLink FTP
    with pymavlink's own client)."""
    from firmware_py.shipped_policies import shipped_policy

    port, start, tmp = rig
    (tmp / "storage" / "policies").mkdir(parents=True)
    (tmp / "storage" / "policies" / "active.qtab").write_bytes(shipped_policy("sector").read_bytes())
    r = start()
    code, out = qnav(port, "mission", "upload", "--targets", "B,C", "--no-plan")
    assert code == 0 and "2 waypoints" in out, out
    stored = list(r.vehicle.mission)  # lat/lon around the robot's origin: back within 6 mm
    want = [robot_spec.cell_center_mm(c, row, 10) for c, row in ((9, 0), (0, 9))]
    assert len(stored) == 2 and all(math.dist(a, b) < 7 for a, b in zip(stored, want, strict=True)), stored
    code, out = qnav(port, "mission", "upload", "--targets", "A", "--map", "paper10", "--cell-size", "0.4")
    assert code == 2 and out.count("\n") == 1, out
    assert ("--map paper10 (10x10 cells of 0.4 m) is not the robot's map paper10 (10x10 cells of 0.5 m)" in out
            and r.vehicle.mission == stored), out  # nothing sent
    assert qnav(port, "mission", "upload", "--targets", "A", "--map", "paper10", "--no-plan")[0] == 0  # the same map: fine
    r.vehicle.st.policy_id = 0x12340000  # the robot says it runs another policy than its file
    code, out = qnav(port, "mission", "upload", "--targets", "A")
    assert code == 2 and "the robot runs policy 0x1234" in out and "give --map" in out, out
