"""`qnav monitor --plain` in a subprocess: over real UDP against a pymavlink
rover, and replaying a tlog; plus the command's input errors."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from ground_station.subprocs import free_udp_port
from tests.support.rover_script import RoverScript, UdpRover, write_tlog

QNAV = str(Path(sys.executable).parent / "qnav")


def qnav(*args, timeout=60):
    return subprocess.run([QNAV, *args], capture_output=True, text=True, timeout=timeout)


def fields(line: str) -> dict[str, str]:
    return dict(re.findall(r"(\w+)=(\S+)", line))


@pytest.fixture(scope="module")
def tlog(tmp_path_factory):
    path = tmp_path_factory.mktemp("plain") / "run.tlog"
    write_tlog(path, RoverScript())
    return path


def test_plain_replay_prints_one_line_per_recorded_second(tlog):
    script = RoverScript()
    r = qnav("monitor", "--replay", str(tlog), "--plain", "--speed", "0")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    assert len(lines) == int(script.t_end) + 1  # one per second + the final line
    first, last = fields(lines[0]), fields(lines[-1])
    assert (first["mode"], first["armed"], first["ctrl"]) == ("Hold", "no", "STANDBY")
    assert (last["x"], last["y"], last["reached"], last["policy"]) == ("4.75", "4.75", "2", "0x00001092")  # 4242, exact from POLICY_ID_HI/LO
    fault_second = int(script.t_fault) + 1
    assert fields(lines[fault_second - 1])["ctrl"] == "FAULT" and fields(lines[fault_second - 1])["failsafe"] == "yes"
    assert {fields(ln)["ctrl"] for ln in lines} >= {"STANDBY", "DRIVING", "FAULT", "GOAL_REACHED"}


def test_plain_live_over_udp_records_and_reports(tmp_path):
    port = free_udp_port()
    rover = UdpRover(port, speed=4.0)
    rover.start()
    live_tlog = tmp_path / "live.tlog"
    try:
        r = qnav("monitor", "--mavlink", f"udpin:127.0.0.1:{port}", "--plain", "--duration", "6",
                 "--tlog", str(live_tlog), "--map", "none")
    finally:
        rover.stop()
    assert r.returncode == 0, r.stderr
    lines = [fields(ln) for ln in r.stdout.strip().splitlines()]
    assert 3 <= len(lines) <= 8
    heard = [ln for ln in lines if ln["mode"] != "-"]
    assert heard and all(float(ln["hb_age"].rstrip("s")) < 2 for ln in heard[1:])
    assert len({(ln["x"], ln["y"]) for ln in heard}) >= 2  # the pose moved while we watched
    assert any(ln["armed"] == "yes" and ln["mode"] == "Auto" for ln in heard)
    # the monitor kept the robot's GCS failsafe quiet and asked for the policy id
    assert rover.received.get("HEARTBEAT", 0) >= 3
    assert rover.received.get("PARAM_REQUEST_READ", 0) >= 1
    # the session log holds both directions and makes a report
    assert live_tlog.stat().st_size > 1000
    rep = qnav("report", str(live_tlog), "--out", str(tmp_path / "rep"), "--map", "none", "--json")
    assert rep.returncode == 0, rep.stderr
    assert (tmp_path / "rep" / "trajectory.png").exists()


@pytest.mark.parametrize("args, needle", [
    (["--replay", "/nonexistent.tlog", "--plain"], "no such tlog"),
    (["--replay", "x.tlog", "--mavlink", "udpin:127.0.0.1:9"], "cannot be combined"),
    (["--replay", "x.tlog", "--speed", "-1"], "--speed must be >= 0"),
    (["--map", "no-such-map"], "--map no-such-map"),
    (["--plain", "--duration", "0"], "--duration must be > 0"),
])
def test_bad_input_is_one_line_exit_2(args, needle, tmp_path):
    r = subprocess.run([QNAV, "monitor", *args], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert needle in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_bad_signing_key_file(tmp_path):
    key = tmp_path / "empty.key"
    key.write_bytes(b"")
    r = qnav("monitor", "--plain", "--duration", "1", "--no-tlog", "--signing-key", str(key),
             "--mavlink", f"udpin:127.0.0.1:{free_udp_port()}")
    assert r.returncode == 2 and "empty" in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("words", ["item 2: stalled: blocked ahead, 412 mm to go",
                                   "GCS failsafe: no GCS heartbeat for 5000 ms, Hold"])
def test_until_done_ends_when_the_robot_holds_for_good(tmp_path, words):
    # a pymavlink vehicle on UDP loopback: armed in Auto, then the robot's words (a stall, or the GCS
    # failsafe's Hold: firmware_py/mavlink/node.py check_failsafe) and Hold; the monitor ends with them
    # (exit 3) instead of waiting out --duration
    import threading
    import time

    from pymavlink import mavutil

    port = free_udp_port()
    stop = threading.Event()

    def vehicle() -> None:
        conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
        t0 = time.monotonic()
        try:
            while not stop.wait(0.2):
                held = time.monotonic() - t0 > 1.5
                armed = mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GROUND_ROVER, mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                        armed, 4 if held else 10, mavutil.mavlink.MAV_STATE_ACTIVE)
                if held:
                    conn.mav.statustext_send(mavutil.mavlink.MAV_SEVERITY_WARNING, words.encode())
        finally:
            conn.close()

    th = threading.Thread(target=vehicle, daemon=True)
    th.start()
    t0 = time.monotonic()
    try:
        r = qnav("monitor", "--mavlink", f"udpin:127.0.0.1:{port}", "--plain", "--until-done", "--duration", "30",
                 "--no-tlog", "--map", "none")
    finally:
        stop.set()
        th.join(5)
    assert r.returncode == 3, (r.stdout, r.stderr)
    assert f"the robot stopped: {words}" in r.stderr
    assert time.monotonic() - t0 < 25  # not the --duration


def test_a_failsafe_that_only_reports_is_not_a_hold():
    from ground_station.mavlink.statustext import holds_for_good

    assert holds_for_good("GCS failsafe: no GCS heartbeat for 5000 ms, disarm")
    assert not holds_for_good("GCS failsafe: no GCS heartbeat for 5000 ms, none")  # FS_GCS_ACTION 0: it drives on
    assert not holds_for_good("GCS failsafe cleared")
