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
import subprocess
from pathlib import Path

import pytest

from ground_station.subprocs import free_udp_port
from tests.support.doc_page import PageRun
from tests.support.doc_page import blocks as page_blocks

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "walkthrough.md"


def blocks() -> list[str]:
    return page_blocks(PAGE)


def test_the_page_has_the_steps_this_test_relies_on():
    found = blocks()
    assert found[0].startswith("# setup") and sum(b.startswith("# terminal 2") for b in found) == 1
    assert "14555" in "".join(found)


@pytest.mark.slow
def test_walkthrough_runs_from_the_map_to_the_report(tmp_path):
    port = free_udp_port()

    def after(script: str, done: subprocess.CompletedProcess) -> None:
        if "qnav monitor" in script:  # --until-done: ended by the robot's "mission complete"
            last = [x for x in done.stdout.splitlines() if x.startswith("[")][-1]
            assert "mission=3/3 reached=3" in last, done.stdout[-2000:]

    page = PageRun(PAGE, tmp_path, lambda block: block.replace("14555", str(port)))
    try:
        page.run(after)
    finally:
        code = page.stop()
    sitl_out = page.sitl_out
    assert code == 0, sitl_out.read_text()[-3000:]
    summary = json.loads((tmp_path / "runs" / "report" / "summary.json").read_text())
    assert summary["goals_reached"] == 3 and summary["map"] == "warehouse.map"
    for png in ("runs/warehouse/policy.png", "runs/report/trajectory.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", png
    for name in ("sim.log", "robot.log", "can.blf", "trajectory.csv", "run.mcap"):
        assert (tmp_path / "runs" / "sitl" / name).stat().st_size > 0, name
    logs = (tmp_path / "runs" / "sitl" / "robot.log").read_text() + (tmp_path / "runs" / "sitl" / "sim.log").read_text()
    assert "Traceback" not in logs
