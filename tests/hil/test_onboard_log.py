"""The robot's own log (firmware_py/onboard_log.py): transitions, faults and a stats line per second
under its storage root, size-capped and rotated, fetched over MAVLink FTP with `qnav log list|pull`."""

from __future__ import annotations

import logging
import subprocess
import sys
import time
from pathlib import Path

from firmware_py.onboard_log import OnboardLog
from ground_station.subprocs import free_udp_port, stop_process

BIN = Path(sys.executable).parent


def test_the_log_rotates_within_its_cap_and_never_blocks(tmp_path):
    lines = iter(range(10**9))
    onboard = OnboardLog(tmp_path, stats=lambda: f"stats n={next(lines)}", max_bytes=2000, backups=2,
                         period_s=0.01).start()
    log = logging.getLogger("qnav.controller")
    t0 = time.perf_counter()
    for i in range(3000):
        log.info("t=%d us DRIVING -> HOLD: record %d", i, i)
    assert time.perf_counter() - t0 < 2.0  # queued, not written, by the caller
    time.sleep(0.1)
    onboard.stop()
    files = sorted((tmp_path / "logs").iterdir())
    assert [f.name for f in files] == ["robot.log", "robot.log.1", "robot.log.2"]
    assert all(f.stat().st_size <= 2000 + 200 for f in files)  # the cap (one record over at most)
    text = "".join(f.read_text() for f in files)
    assert "record 2999" in text and "stats n=" in text  # the newest records are kept


def test_qnav_log_list_and_pull_fetch_the_robots_log_over_mavlink(tmp_path):
    port = free_udp_port()
    storage = tmp_path / "robot"
    robot = subprocess.Popen([BIN / "qnav-robot", "--can", "virtual:onboard-log", "--storage", storage,
                              "--mavlink", f"udpout:127.0.0.1:{port}", "-q"],
                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        url = f"udpin:127.0.0.1:{port}"
        log = storage / "logs" / "robot.log"
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and "stats state=" not in (log.read_text() if log.exists() else ""):
            time.sleep(0.1)  # the first stats line (1 s after boot)
        ls = subprocess.run([BIN / "qnav", "log", "list", "--mavlink", url], capture_output=True, text=True,
                            timeout=60)
        assert ls.returncode == 0, ls.stderr
        assert "/logs/robot.log" in ls.stdout and "1 file(s)" in ls.stdout
        pull = subprocess.run([BIN / "qnav", "log", "pull", "--mavlink", url, "--out", tmp_path / "got"],
                              capture_output=True, text=True, timeout=60)
        assert pull.returncode == 0, pull.stderr
        text = (tmp_path / "got" / "robot.log").read_text()
        assert "BOOT -> STANDBY" in text and "stats state=" in text and "onboard log started" in text
        missing = subprocess.run([BIN / "qnav", "log", "pull", "--mavlink", url, "nope.log"], capture_output=True,
                                 text=True, timeout=60)
        assert missing.returncode != 0 and "no /logs/nope.log on the robot (it has robot.log)" in missing.stderr
    finally:
        stop_process(robot)
    assert "stopped: " in (storage / "logs" / "robot.log").read_text()  # the last line, written on the way out
