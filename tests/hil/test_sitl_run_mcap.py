"""`qnav sitl`'s run.mcap is the whole run (issue 46, items 3 and 4): the robot's telemetry, recorded
by sitl's own relay whatever ground station connects, beside CAN, ground truth, the map and robot.log,
so every topic of the shipped Foxglove layout is there, as in `qnav demo`'s; and Ctrl-C says at once
that it stops and writes it, with progress while it is written."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest

from ground_station import cli
from ground_station.maps import load_map
from tests.hil.test_sitl import SitlProcess
from tests.support.mcap_check import check_layout_against_mcap, check_run_mcap

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_sitl_run_mcap_holds_every_layout_topic_and_ctrl_c_says_so_at_once(tmp_path):
    sitl = SitlProcess(tmp_path, "--speed", "2")
    try:
        sitl.wait_up()
        gcs = ["--mavlink", f"udpout:127.0.0.1:{sitl.port}", "--no-tlog", "--timeout", "20"]
        for argv in (["mission", "upload", "--targets", "A,B"], ["arm"], ["mode", "auto"]):
            assert cli.main([*argv, *gcs]) == 0, argv
        time.sleep(6.0)  # it drives a while (motor commands on the bus, poses, scans)
        sitl.proc.send_signal(signal.SIGINT)  # Ctrl-C
        t0 = time.monotonic()
        sitl.expect(r"qnav sitl: stopping the sim and the robot, then writing run\.mcap", timeout_s=5)
        first = time.monotonic() - t0
        sitl.expect(r"qnav sitl: writing .*run\.mcap from mavlink\.tlog, can\.blf.*: 0%", timeout_s=60)
        sitl.expect(r"qnav sitl: wrote .*run\.mcap in [0-9.]+ s: telemetry", timeout_s=120)
        sitl.proc.wait(timeout=30)  # one Ctrl-C is enough: it ends by itself
    finally:
        code = sitl.stop()
    assert code == 0, "\n".join(sitl.log[-30:])
    assert first <= 1.0, first
    out = sitl.out
    counts = check_run_mcap(out / "run.mcap", out / "mavlink.tlog", out / "can.blf", out / "trajectory.csv",
                            load_map("paper10"))
    check_layout_against_mcap(ROOT / "ground_station" / "logs" / "foxglove_layout.json", out / "run.mcap")
    for topic in ("/pose", "/scan", "/mission", "/vehicle", "/location", "/log", "/robot_log", "/can/MotorCommand",
                  "/truth", "/map"):
        assert counts.get(topic, 0) > 0, (topic, sorted(counts))
