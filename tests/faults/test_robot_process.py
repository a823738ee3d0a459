"""The fault rigs' robot process (ground_station/lab/faults/common.py): `start()` returns once the
robot is READY (its MAVLink port bound), and a port picked for it but taken before its bind by a
process beside it costs a restart on another port, not the trial (a fresh-clone make test lost one
so). A real qnav-robot on UDP loopback; the "process beside it" is a socket this test holds."""

import errno
import socket

import pytest

from ground_station.lab.faults import common
from ground_station.lab.faults.common import RobotProcess
from ground_station.mavlink.link import Link
from ground_station.subprocs import free_udp_port

pytestmark = pytest.mark.timeout(120)


def _bound(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError as exc:
            assert exc.errno == errno.EADDRINUSE, exc
            return True
    return False


def test_start_returns_with_the_mavlink_port_bound(tmp_path):
    with RobotProcess(tmp_path / "robot", log=tmp_path / "robot.log") as robot:
        assert robot.alive and _bound(robot.port), robot.log_tail()


def test_a_picked_port_taken_before_the_bind_costs_a_restart_on_another(tmp_path, monkeypatch):
    taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    taken.bind(("127.0.0.1", 0))
    picks = iter([taken.getsockname()[1]])
    monkeypatch.setattr(common, "free_udp_port", lambda: next(picks, None) or free_udp_port())
    try:
        with RobotProcess(tmp_path / "robot", log=tmp_path / "robot.log") as robot:
            assert robot.port != taken.getsockname()[1] and robot.alive, robot.log_tail()
            assert "Address already in use" in robot.log_text()  # the first start lost the race
            link = Link(robot.url, tlog=False)
            try:
                link.connect(20.0)  # the robot heard on its new port
            finally:
                link.close()
    finally:
        taken.close()


def test_a_port_given_by_the_caller_is_not_changed(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        robot = RobotProcess(tmp_path / "robot", port=port, log=tmp_path / "robot.log").start()
        try:
            assert robot.wait(20) == 2 and robot.port == port, robot.log_tail()
        finally:
            robot.stop()
