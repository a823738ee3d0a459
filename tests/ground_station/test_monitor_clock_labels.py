"""`qnav monitor --plain` names its clocks (issue 46): a line's stamp says it is the robot's clock
(`--duration` is wall time, the robot's clock may run faster: `qnav sitl --speed 4`), and the
"waiting for a HEARTBEAT" line names the URL and where it came from."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from ground_station.subprocs import free_udp_port
from tests.support.rover_script import UdpRover

QNAV = str(Path(sys.executable).parent / "qnav")


def test_the_stamps_say_robot_clock_and_the_help_says_duration_is_wall_time(tmp_path):
    port = free_udp_port()
    rover = UdpRover(port, speed=4.0)
    rover.start()
    try:
        r = subprocess.run([QNAV, "monitor", "--mavlink", f"udpin:127.0.0.1:{port}", "--plain", "--duration", "4",
                            "--no-tlog"], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    finally:
        rover.stop()
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    assert lines and all(re.match(r"^\[(robot|recv) +[0-9.]+s\] ", ln) for ln in lines), lines
    assert any(ln.startswith("[robot ") for ln in lines), lines
    helptext = subprocess.run([QNAV, "monitor", "--help"], capture_output=True, text=True, timeout=60).stdout
    assert "wall-clock seconds; line stamps are the robot's clock" in " ".join(helptext.split())


def test_waiting_for_a_robot_names_the_url_and_where_it_came_from(tmp_path):
    url = f"udpin:127.0.0.1:{free_udp_port()}"
    r = subprocess.run([QNAV, "monitor", "--mavlink", url, "--plain", "--timeout", "2", "--no-tlog"],
                       capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert r.returncode == 4
    waiting = [ln for ln in r.stderr.splitlines() if "waiting for a HEARTBEAT" in ln]
    assert waiting and f"on {url}" in waiting[0] and "from --mavlink" in waiting[0], r.stderr
