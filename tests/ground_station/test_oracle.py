"""The privileged planner of `qnav bench ceiling` (ground_station/lab/nav/oracle.py): what it finds
on worlds where the answer is known by hand, and the bench's own figures on a real scenario."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from ground_station.lab.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, PERIOD_S
from ground_station.lab.nav.oracle import mover_tracks, solve
from ground_station.lab.nav.scenario import Episode
from ground_station.maps import GridMap

CELL = 500.0


def centre(gm: GridMap, col: int, row: int) -> tuple[float, float]:
    return (col + 0.5) * CELL, (gm.occ.shape[0] - row - 0.5) * CELL


def grid(rows: list[str]) -> GridMap:
    return GridMap("t", np.array([[ch == "@" for ch in r] for r in rows]), cell_size_m=CELL / 1000)


def episode(gm: GridMap, start: tuple[float, float], waypoints: list[tuple[float, float]],
            movers: list[tuple[float, ...]] = ()) -> Episode:  # type: ignore[assignment]
    return Episode(map=gm.name, start=(start[0], start[1], 0.0), goal=(0, 0), goal_mm=waypoints[-1],
                   waypoints=list(waypoints), movers=list(movers))


def oracle(ep: Episode, gm: GridMap) -> int:
    return solve(ep, gm, 150, BUDGET_BASE, BUDGET_FACTOR, PERIOD_S)


ROOM = grid(["@@@@@@@@",
             "@......@",
             "@......@",
             "@......@",
             "@@@@@@@@"])


def test_an_empty_room_takes_the_straight_drive_at_full_speed() -> None:
    x, y = centre(ROOM, 1, 2)
    # 1000 mm along x: the goal's tolerance (150 mm) is met 900 mm on, 9 steps of 5 periods
    assert oracle(episode(ROOM, (x, y), [(x + 1000, y)]), ROOM) == 45
    # through a waypoint 400 mm up first, in order: 3 steps up (100 mm off it), then 9 along and 2 down
    # (141 mm off the goal)
    via = oracle(episode(ROOM, (x, y), [(x, y + 400), (x + 1000, y)]), ROOM)
    assert via == (3 + 9 + 2) * 5


# a one-cell corridor (row 1) closed at both ends; the robot comes in from below at column 9
CORRIDOR = grid(["@@@@@@@@@@@@",
                 "@..........@",
                 "@@@@@@@@@.@@",
                 "@@@@@@@@@.@@",
                 "@@@@@@@@@@@@"])


def corridor_episode(speed: float) -> Episode:
    gm = CORRIDOR
    mx, my = centre(gm, 4, 1)
    return episode(gm, centre(gm, 9, 3), [centre(gm, 9, 1), centre(gm, 1, 1)], [(mx, my, speed, 0.0, 150.0, 0.0)])


def test_a_walker_in_the_only_corridor_is_followed_if_it_is_slower() -> None:
    # the mover walks the corridor end to end for ever: the robot gets in behind it as it passes the
    # door going away, and reaches the far end first only if the walker does not catch up
    slow = oracle(corridor_episode(300.0), CORRIDOR)
    fast = oracle(corridor_episode(600.0), CORRIDOR)
    empty = oracle(episode(CORRIDOR, centre(CORRIDOR, 9, 3), [centre(CORRIDOR, 9, 1), centre(CORRIDOR, 1, 1)]),
                   CORRIDOR)
    assert empty > 0 and slow > empty  # it waited for its moment
    assert fast == -1


def test_the_walkers_track_is_the_movers_own_model() -> None:
    gm = CORRIDOR
    ep = corridor_episode(600.0)
    tracks = mover_tracks(np.asarray([ep.movers[0]], dtype=np.float64), gm.occ.astype(np.uint8), CELL,
                          np.zeros((0, 3)), 400, PERIOD_S)
    xs = tracks[:, 0, 0]
    assert tracks.shape == (401, 1, 3)
    assert np.all(np.abs(np.diff(xs)) <= 600.0 * PERIOD_S + 1e-9)  # never faster than its speed
    # to and fro between the corridor's end walls: it turns back within a step of touching one
    lo, hi = xs.min(), xs.max()
    assert CELL + 150 <= lo < CELL + 150 + 30 and 11 * CELL - 150 - 30 < hi <= 11 * CELL - 150


def test_bench_ceiling_reports_the_oracle_beside_the_controllers(tmp_path) -> None:
    out = tmp_path / "c.json"
    r = subprocess.run([sys.executable, "-m", "ground_station", "bench", "ceiling", "--map", "maze-12x12-s306",
                        "--obstacles", "6", "--movers", "3", "--no-yield", "--episodes", "4", "--controllers",
                        "seek_local", "--workers", "1", "--json", str(out)], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    assert "oracle (privileged)" in r.stdout and "seek_local" in r.stdout
    res = json.loads(out.read_text())
    rows = res["episodes"]
    assert [row["index"] for row in rows] == [0, 1, 2, 3]
    solved = sum(row["oracle_s"] is not None for row in rows)
    assert res["oracle"]["solved"] == solved == res["per_map"]["maze-12x12-s306"]["oracle"]
    won = sum(row["seek_local"] == "success" for row in rows)
    s = res["seek_local"]
    assert round(s["success_rate"] * 4) == won
    assert s["failed_oracle_solved"] + s["failed_oracle_not"] == 4 - won
