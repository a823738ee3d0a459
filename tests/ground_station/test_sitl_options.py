"""`qnav sitl`'s pure parts: the ground station's side of the robot's
connection string, option checks, and the connection help it prints."""

from __future__ import annotations

from pathlib import Path

import pytest

from ground_station.sitl import (
    SitlError,
    SitlInfo,
    SitlOptions,
    WaitResult,
    connection_help,
    gcs_side,
    validate,
)


@pytest.mark.parametrize(("robot", "gcs"), [
    ("udpin:127.0.0.1:14555", "udpout:127.0.0.1:14555"),
    ("udpout:127.0.0.1:14550", "udpin:127.0.0.1:14550"),
    ("tcpin:0.0.0.0:5760", "tcp:0.0.0.0:5760"),
    ("/dev/ttyUSB0", "/dev/ttyUSB0"),
])
def test_gcs_side_of_the_robot_url(robot, gcs):
    assert gcs_side(robot) == gcs


@pytest.mark.parametrize(("opts", "why"), [
    (SitlOptions(speed=-1), "--speed must be a positive number"),
    (SitlOptions(speed=float("inf")), "--speed must be a positive number"),
    (SitlOptions(duration_s=0), "--duration must be positive"),
    (SitlOptions(can="virtual:x"), "a virtual bus does not reach another process"),
    (SitlOptions(mavlink="udpin:127.0.0.1"), "expected udpin:HOST:PORT"),
    (SitlOptions(mavlink="udpin:127.0.0.1:99999"), "port must be a number 1-65535"),  # link.check_url's words
    (SitlOptions(mavlink="bogus://foo"), "--mavlink bogus://foo: expected"),
])
def test_bad_options_are_refused_with_the_reason(opts, why):
    with pytest.raises(SitlError, match=why.replace("(", r"\(").replace("+", r"\+")):
        validate(opts)


def info(can_spec: str, mavlink: str = "udpin:127.0.0.1:14555", hub: bool = False) -> SitlInfo:
    return SitlInfo(run_dir=Path("runs/sitl-x"), mavlink=mavlink, gcs_url=gcs_side(mavlink), can_spec=can_spec,
                    hub=hub, policy="p.qtab", start="2.75,2.75,0", sysid=1)


def test_connection_help_names_every_client_and_the_can_tools():
    text = "\n".join(connection_help(info("remote:ws://127.0.0.1:4000/", hub=True)))
    assert "mavproxy.py --master=udpout:127.0.0.1:14555" in text
    assert 'system_address="udpout://127.0.0.1:14555"' in text
    assert "qnav monitor --mavlink udpout:127.0.0.1:14555" in text
    assert "target host 127.0.0.1:14555" in text
    assert "CAN bus: remote:ws://127.0.0.1:4000/ (python-can-remote hub)" in text
    assert "cantools monitor -i remote -c ws://127.0.0.1:4000/ " in text and "qnav.dbc" in text
    text = "\n".join(connection_help(info("socketcan:vcan0")))
    assert "candump -L vcan0" in text and "cansniffer -c vcan0" in text
    assert "cantools monitor -i socketcan -c vcan0" in text
    text = "\n".join(connection_help(info("socketcan:vcan0", mavlink="udpout:127.0.0.1:14550")))
    assert "QGroundControl  connects by itself" in text and "--master=udpin:127.0.0.1:14550" in text


def test_wait_says_whether_a_child_died_or_the_duration_ran_out(tmp_path):
    """The exit status of `qnav sitl` (1: a process died) comes from this flag, not from the wording."""
    import sys

    from ground_station.sitl import Sitl

    sitl = Sitl(SitlOptions(duration_s=0.3))
    try:
        assert sitl.wait(poll_s=0.05) == WaitResult("duration reached", child_died=False)
        sitl.procs.start("robot", [sys.executable, "-c", "import sys; print('bye'); sys.exit(3)"],
                         tmp_path / "robot.log")
        sitl.opts.duration_s = 30.0
        result = sitl.wait(poll_s=0.05)
        assert result.child_died and result.reason.startswith("robot exited with status 3")
    finally:
        sitl.stop()


def test_the_robot_is_up_once_it_leaves_boot(tmp_path):
    """`qnav sitl` says the robot is up (and a GCS may arm it) only once its HEARTBEAT is past BOOT,
    i.e. after its first control tick: a robot heard still booting refuses to arm ("still booting",
    seen beside a busy suite). A pymavlink vehicle on UDP loopback plays the robot."""
    import os
    import threading
    import time

    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    from ground_station.sitl import Sitl
    from ground_station.subprocs import free_udp_port

    port = free_udp_port()
    robot = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1)
    M = mavutil.mavlink
    boot_until = time.monotonic() + 1.5
    stop = threading.Event()

    def vehicle() -> None:
        while not stop.is_set():
            state = M.MAV_STATE_BOOT if time.monotonic() < boot_until else M.MAV_STATE_STANDBY
            robot.mav.heartbeat_send(M.MAV_TYPE_GROUND_ROVER, M.MAV_AUTOPILOT_GENERIC, 0, 0, state)
            robot.recv_match(blocking=True, timeout=0.1)  # learns the prober's address
            time.sleep(0.1)

    thread = threading.Thread(target=vehicle, daemon=True)
    thread.start()
    sitl = Sitl(SitlOptions())
    info = SitlInfo(tmp_path, f"udpin:127.0.0.1:{port}", f"udpout:127.0.0.1:{port}", "virtual:x", False, "none",
                    "0,0,0", logs={"robot": tmp_path / "robot.log", "sim": tmp_path / "sim.log"})
    try:
        t0 = time.monotonic()
        assert sitl._probe(info) == 1
        assert time.monotonic() >= boot_until - 0.05, f"up after {time.monotonic() - t0:.2f} s, still booting"
        boot_until = time.monotonic() + 1e9  # booting for good from here: the probe gives up, saying so
        sitl.opts.probe_timeout_s = 1.5
        with pytest.raises(SitlError, match="still booting"):
            sitl._probe(info)
    finally:
        stop.set()
        thread.join(timeout=2)
        robot.close()
        sitl.stop()
