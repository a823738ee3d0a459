"""docs/walkthrough.md, run as a new user would run it (issue 30 item 8): every ```sh block in
order, with bash, in a scratch folder, the venv's programs on the PATH. The `# setup` block
(make venv, activate, cd) is what this test's own environment already is; the `# terminal 2`
block (`qnav sitl`) runs in the background until the end, then gets Ctrl-C (SIGINT to its process
group, as a terminal sends it). The robot's port is replaced by a free one (never 14555 or 14550,
which other programs on the machine may use). Checked: every block exits 0, the mission reaches
its three targets, the report and the pictures the page shows are written, and the sitl stops
cleanly with its run folder complete."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ground_station.subprocs import free_udp_port

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "walkthrough.md"
BLOCK = re.compile(r"```sh\n(.*?)```", re.S)


def blocks() -> list[str]:
    return BLOCK.findall(PAGE.read_text())


def test_the_page_has_the_steps_this_test_relies_on():
    found = blocks()
    assert found[0].startswith("# setup") and sum(b.startswith("# terminal 2") for b in found) == 1
    assert "14555" in "".join(found)


@pytest.mark.slow
def test_walkthrough_runs_from_the_map_to_the_report(tmp_path):
    port = free_udp_port()
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    env.pop("QNAV_MAVLINK", None)
    sitl: subprocess.Popen | None = None
    sitl_out = tmp_path / "sitl.out"
    try:
        for block in blocks():
            script = block.replace("14555", str(port))
            if script.startswith("# setup"):
                continue
            if script.startswith("# terminal 2"):
                sitl = subprocess.Popen(["bash", "-c", script], cwd=tmp_path, env=env, start_new_session=True,
                                        stdout=sitl_out.open("w"), stderr=subprocess.STDOUT)
                deadline = time.monotonic() + 90
                while "Ctrl-C stops every process" not in sitl_out.read_text():
                    assert sitl.poll() is None and time.monotonic() < deadline, sitl_out.read_text()[-3000:]
                    time.sleep(0.2)
                continue
            # the commands of one block run in one shell, as typed in one terminal
            done = subprocess.run(["bash", "-e", "-c", script], cwd=tmp_path, env=env, capture_output=True,
                                  text=True, timeout=240)
            assert done.returncode == 0, (script, done.stdout[-3000:], done.stderr[-3000:])
            if "qnav monitor" in script:  # --until-done: ended by the robot's "mission complete"
                last = [x for x in done.stdout.splitlines() if x.startswith("[")][-1]
                assert "mission=3/3 reached=3" in last, done.stdout[-2000:]
    finally:
        if sitl is not None and sitl.poll() is None:
            os.killpg(sitl.pid, signal.SIGINT)  # Ctrl-C in its terminal
            try:
                sitl.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(sitl.pid, signal.SIGKILL)
                raise
    assert sitl is not None and sitl.returncode == 0, sitl_out.read_text()[-3000:]
    summary = json.loads((tmp_path / "runs" / "report" / "summary.json").read_text())
    assert summary["goals_reached"] == 3 and summary["map"] == "warehouse.map"
    for png in ("runs/warehouse/policy.png", "runs/report/trajectory.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
    for name in ("sim.log", "robot.log", "can.blf", "trajectory.csv", "run.mcap"):
        assert (tmp_path / "runs" / "sitl" / name).stat().st_size > 0, name
    logs = (tmp_path / "runs" / "sitl" / "robot.log").read_text() + (tmp_path / "runs" / "sitl" / "sim.log").read_text()
    assert "Traceback" not in logs
