"""Issue 47, the twin-to-robot gap on new maps: a sector policy trained with the shipped recipe on a
small map the project has never seen completes the walkthrough's mission through all its targets in
`qnav sitl --lockstep`, with the walkthrough's commands (docs/walkthrough.md: `qnav map upload`,
`qnav upload --activate`, `qnav mission upload --targets`, `qnav arm`, `qnav mode auto`, `qnav monitor
--until-done`).

The map is generated here (seeded wall segments on a 12 x 10 grid of 0.5 m cells, targets at the four
corners). Its first leg, from the sim's start to B, runs under a wall segment: the straight line from
the start to B passes 0.1 m under the segment's end, and the one-cell corridor along the north edge
leads to B. The sector table steers to the bearing of the current mission item; trained and evaluated
in the twin on the ground station planner's waypoints (`qnav eval`: 0.989 on this map), it stalled at
that wall end ("stalled: no progress") when the mission held the targets themselves (the twin's
`direct` column: 0.455). `qnav mission upload --targets` now plans the waypoints for a robot whose
policy steers to them (ground_station/commands/mission.py), as `--plan` does.

Checked against the sim's ground truth (runs/sitl/trajectory.csv): the robot passes within 0.25 m of
every target's centre, in the mission's order, and the robot's last reported pose (the monitor's last
line) is within 0.15 m of where the sim says it stands after the mission."""

from __future__ import annotations

import csv
import json
import math
import os
import random
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ground_station.subprocs import free_udp_port
from tests.support.doc_page import interrupt

BIN = Path(sys.executable).parent
W, H, CELL_M = 12, 10, 0.5
TARGETS = {"A": (0, 0), "B": (W - 1, 0), "C": (W - 1, H - 1), "D": (0, H - 1)}
MISSION = "B,C,D,A"
POSE = re.compile(r" x=(-?[\d.]+) y=(-?[\d.]+) hdg=")


def new_map(seed: int) -> str:
    """A MovingAI map of W x H cells with five straight wall segments of 2-4 cells, placed by `seed`
    inside the border ring (so the four corner targets and the map's edge rows stay free)."""
    rng = random.Random(seed)
    grid = [["."] * W for _ in range(H)]
    for _ in range(5):
        horizontal = rng.random() < 0.5
        n = rng.randint(2, 4)
        if horizontal:
            r, c = rng.randint(1, H - 2), rng.randint(1, W - 1 - n)
            for k in range(n):
                grid[r][c + k] = "@"
        else:
            c, r = rng.randint(1, W - 2), rng.randint(1, H - 1 - n)
            for k in range(n):
                grid[r + k][c] = "@"
    return f"type octile\nheight {H}\nwidth {W}\nmap\n" + "\n".join("".join(row) for row in grid) + "\n"


def centre(cell: tuple[int, int]) -> tuple[float, float]:
    return (cell[0] + 0.5) * CELL_M, (H - cell[1] - 0.5) * CELL_M


def _wall_distance(gm, x: float, y: float) -> float:
    """Distance (m) from (x, y) to the nearest wall cell of `gm` (0 inside one)."""
    best = math.inf
    for r, c in zip(*gm.occ.nonzero(), strict=True):
        x0, y0 = c * CELL_M, (H - r - 1) * CELL_M
        dx, dy = max(x0 - x, 0.0, x - x0 - CELL_M), max(y0 - y, 0.0, y - y0 - CELL_M)
        best = min(best, math.hypot(dx, dy))
    return best


def test_the_generated_map_is_new_and_its_first_leg_passes_a_wall_end():
    from ground_station.maps import load_map
    from ground_station.maps.builtin import builtin_names
    from ground_station.maps.movingai import parse_map
    from sim_bridge.world import World

    gm = parse_map(new_map(47), "new.map", CELL_M)
    assert gm.occ.sum() >= 10 and not any(gm.occ[r, c] for c, r in TARGETS.values())
    for name in builtin_names():  # none of the project's maps
        assert load_map(name).occ.shape != gm.occ.shape or (load_map(name).occ != gm.occ).any(), name
    # the straight line from the sim's start (the free cell nearest the centre) to B passes a wall end
    # nearer than the body's radius (0.15 m): a mission of the targets alone leads the robot into it
    start = World(gm.occ, CELL_M).default_start()
    bx, by = centre(TARGETS["B"])
    near = min(_wall_distance(gm, start.x + f * (bx - start.x), start.y + f * (by - start.y))
               for f in (i / 200 for i in range(201)))
    assert 0 < near < 0.15, near


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_sector_policy_trained_on_a_new_map_completes_the_walkthrough_mission(tmp_path):
    (tmp_path / "new.map").write_text(new_map(47))
    (tmp_path / "new.targets.json").write_text(json.dumps({k: list(v) for k, v in TARGETS.items()}))
    port = free_udp_port()
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ['PATH']}",
               QNAV_MAVLINK=f"udpout:127.0.0.1:{port}")

    def qnav(*argv: str, timeout: float = 240) -> str:
        done = subprocess.run([BIN / "qnav", *argv], cwd=tmp_path, env=env, capture_output=True, text=True,
                              timeout=timeout)
        assert done.returncode == 0, (argv, done.stdout[-3000:], done.stderr[-3000:])
        return done.stdout

    qnav("train", "--recipe", "shipped-sector", "--map", "new.map", "--out", "runs/sector", "--quiet")
    qnav("export", "runs/sector", "--out", "sector.qtab", "--no-rollouts")
    out = tmp_path / "sitl.out"
    sitl = subprocess.Popen([BIN / "qnav", "sitl", "--map", "new.map", "--policy", "none", "--lockstep",
                             "--speed", "8", "--mavlink", f"udpin:127.0.0.1:{port}", "--out", "runs/sitl"],
                            cwd=tmp_path, env=env, start_new_session=True, stdout=out.open("w"),
                            stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 90
        while "Ctrl-C stops every process" not in out.read_text():
            assert sitl.poll() is None and time.monotonic() < deadline, out.read_text()[-3000:]
            time.sleep(0.2)
        qnav("map", "upload", "new.map")
        qnav("upload", "sector.qtab", "--activate")
        planned = qnav("mission", "upload", "--targets", MISSION)
        qnav("arm")
        qnav("mode", "auto")
        mon = qnav("monitor", "--plain", "--until-done", "--duration", "120", "--no-tlog", timeout=200)
    finally:
        code = interrupt(sitl, out)  # Ctrl-C in its terminal
    assert code == 0, out.read_text()[-3000:]
    last = [x for x in mon.splitlines() if x.startswith("[")][-1]
    m = re.search(r"mission=(\d+)/(\d+) reached=(\d+)", last)
    assert m and m[1] == m[2] == m[3] and "stalls=0" in last, mon[-3000:]
    with open(tmp_path / "runs" / "sitl" / "trajectory.csv", newline="") as f:
        rows = [(float(r["x_m"]), float(r["y_m"])) for r in csv.DictReader(f)]
    i = 0  # every target, in the mission's order, by the sim's ground truth
    for name in MISSION.split(","):
        c = centre(TARGETS[name])
        while i < len(rows) and math.dist(rows[i], c) > 0.25:
            i += 1
        assert i < len(rows), (name, c, rows[-1])
    pose = POSE.search(last)
    assert pose, last
    assert math.dist((float(pose[1]), float(pose[2])), rows[-1]) <= 0.15, (last, rows[-1])
    assert math.dist(rows[-1], centre(TARGETS["A"])) < 0.3, rows[-1]
    assert "steers to the planner's waypoints: planning them" in planned, planned
    logs = "".join((tmp_path / "runs" / "sitl" / n).read_text() for n in ("robot.log", "sim.log"))
    assert "Traceback" not in logs
