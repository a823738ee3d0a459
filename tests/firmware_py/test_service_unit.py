"""Deployment pieces (docs/deploy.md): the shipped systemd unit, and qnav-robot's sd_notify: READY once
running, WATCHDOG=1 only while the control loop ticks, STOPPING on the way out; SIGTERM stops it the
clean way."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from firmware_py.sdnotify import ServiceNotifier

BIN = Path(sys.executable).parent


def _listen(tmp_path: Path) -> tuple[socket.socket, str]:
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(0.05)
    return sock, path


def _drain(sock: socket.socket) -> list[str]:
    out = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except (TimeoutError, BlockingIOError):
            return out


def test_the_watchdog_is_petted_only_while_the_ticks_advance(tmp_path):
    sock, path = _listen(tmp_path)
    ticks = [0]
    n = ServiceNotifier.from_env({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "40000"})
    n.start(lambda: ticks[0])
    for _ in range(10):
        ticks[0] += 1
        time.sleep(0.02)
    moving = [m for m in _drain(sock) if m.startswith("WATCHDOG=1")]
    time.sleep(0.2)  # a control loop that hangs: the count stands still
    stuck = [m for m in _drain(sock) if m.startswith("WATCHDOG=1")]
    n.stop()
    assert len(moving) >= 3 and len(stuck) <= 1  # at most the pet for the last tick before it stopped
    assert _drain(sock)[-1] == "STOPPING=1"
    assert ServiceNotifier.from_env({}).notify("READY=1") is False  # not under systemd: nothing, no error


def test_qnav_robot_under_systemd_notifies_and_stops_cleanly_on_sigterm(tmp_path):
    sock, path = _listen(tmp_path)
    env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000", "PATH": "/usr/bin:/bin"}
    proc = subprocess.Popen([BIN / "qnav-robot", "--can", "virtual:sdnotify", "--mavlink", "none",
                             "--stats-json", tmp_path / "stats.json"], env=env, stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    got: list[str] = []
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and sum(m.startswith("WATCHDOG=1") for m in got) < 4:
        got += _drain(sock)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    got += _drain(sock)
    assert got[0] == "READY=1" and sum(m.startswith("WATCHDOG=1") for m in got) >= 4, got
    assert "STATUS=" in next(m for m in got if m.startswith("WATCHDOG=1"))
    assert got[-1] == "STOPPING=1"
    assert proc.returncode == 130 and (tmp_path / "stats.json").exists(), err[-1000:]  # the Ctrl-C path


def test_the_shipped_unit_is_what_print_unit_prints():
    run = subprocess.run([BIN / "qnav-robot", "--print-unit"], capture_output=True, text=True, timeout=30)
    assert run.returncode == 0
    unit = run.stdout
    for line in ("Type=notify", "WatchdogSec=", "Restart=on-failure", "AmbientCapabilities=CAP_SYS_NICE",
                 "KillSignal=SIGINT", "ExecStart=/opt/qnav/bin/qnav-robot --profile /etc/qnav/robot.toml"):
        assert line in unit
