"""The privileged planner of `qnav bench ceiling` (ground_station/lab/nav/oracle.py) and the same
planner limited to the movers the robot has seen (ground_station/lab/nav/foresight.py): what they
find on worlds where the answer is known by hand, and the bench's own figures on a real scenario."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from ground_station.lab.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, PERIOD_S
from ground_station.lab.nav.foresight import _back_off, sees, solve_seen
from ground_station.lab.nav.oracle import (
    REVERSE_UNITS,
    TURN_UNITS,
    mover_tracks,
    solve,
    solve_kinematic,
    solve_path,
)
from ground_station.lab.nav.scenario import (
    MOVER_SPEED_MM_S,
    Episode,
    MoverStyle,
    episodes,
    rollout_arrays,
)
from ground_station.learn.sector.kernels import GOAL_TOL_MM
from ground_station.learn.sector.twin import disc_hits
from ground_station.maps import GridMap, load_map
from sim_bridge.obstacles import step_movers

CELL = 500.0
PNG = b"\x89PNG\r\n\x1a\n"


def centre(gm: GridMap, col: int, row: int) -> tuple[float, float]:
    return (col + 0.5) * CELL, (gm.occ.shape[0] - row - 0.5) * CELL


def grid(rows: list[str]) -> GridMap:
    return GridMap("t", np.array([[ch == "@" for ch in r] for r in rows]), cell_size_m=CELL / 1000)


def episode(gm: GridMap, start: tuple[float, float], waypoints: list[tuple[float, float]],
            movers: tuple[tuple[float, ...], ...] = ()) -> Episode:
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


def kinematic(ep: Episode, gm: GridMap) -> int:
    return solve_kinematic(ep, gm, 150, BUDGET_BASE, BUDGET_FACTOR, PERIOD_S)


def test_the_robots_moves_turn_in_place_and_reverse_at_the_twins_rates() -> None:
    # quarter turn at 1.23 rad/s: 1.28 s, 25.5 periods -> 6 units of 5; a 100 mm step back at 200 mm/s: 2 units
    assert (TURN_UNITS, REVERSE_UNITS) == (6, 2)
    x, y = centre(ROOM, 1, 2)
    assert kinematic(episode(ROOM, (x, y), [(x + 1000, y)]), ROOM) == 45  # ahead, as the oracle
    # 1000 mm behind: 9 steps back (18 units) beat a half turn (12) and 9 ahead
    assert kinematic(episode(ROOM, (x + 1000, y), [(x, y)]), ROOM) == 9 * REVERSE_UNITS * 5
    # up to the waypoint: a quarter turn and 3 steps; then 2 steps back down and a quarter turn, 9 ahead
    # (141 mm off the goal): 28 units, where the oracle (sideways, turning in no time) took 14
    assert kinematic(episode(ROOM, (x, y), [(x, y + 400), (x + 1000, y)]), ROOM) == (6 + 3 + 4 + 6 + 9) * 5


# a one-cell corridor (row 1) closed at both ends; the robot comes in from below at column 9
CORRIDOR = grid(["@@@@@@@@@@@@",
                 "@..........@",
                 "@@@@@@@@@.@@",
                 "@@@@@@@@@.@@",
                 "@@@@@@@@@@@@"])


def corridor_episode(speed: float) -> Episode:
    gm = CORRIDOR
    mx, my = centre(gm, 4, 1)
    return episode(gm, centre(gm, 9, 3), [centre(gm, 9, 1), centre(gm, 1, 1)], ((mx, my, speed, 0.0, 150.0, 0.0),))


def test_a_walker_in_the_only_corridor_is_followed_if_it_is_slower() -> None:
    # the mover walks the corridor end to end for ever: the robot gets in behind it as it passes the
    # door going away, and reaches the far end first only if the walker does not catch up
    slow = oracle(corridor_episode(300.0), CORRIDOR)
    fast = oracle(corridor_episode(600.0), CORRIDOR)
    empty = oracle(episode(CORRIDOR, centre(CORRIDOR, 9, 3), [centre(CORRIDOR, 9, 1), centre(CORRIDOR, 1, 1)]),
                   CORRIDOR)
    assert empty > 0 and slow > empty  # it waited for its moment
    assert fast == -1
    # the robot's moves: the quarter turn at the door, after it has waited for its moment as well
    assert kinematic(corridor_episode(300.0), CORRIDOR) >= slow + TURN_UNITS * 5
    assert kinematic(corridor_episode(600.0), CORRIDOR) == -1


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


def replay(ep: Episode, gm: GridMap, period: int, way: list[tuple[int, float, float]]) -> None:
    """Drive the oracle's way period by period with the movers' own model stepped with the robot where it
    is (as the twin steps them): no contact, no mover turned or stood for it, the waypoints in order."""
    discs, movers, wps, _, _ = rollout_arrays(ep, True)
    free_walk = mover_tracks(movers, gm.occ.astype(np.uint8), CELL, discs, period, PERIOD_S)
    occ = gm.occ.astype(np.uint8)
    h, w = occ.shape
    assert way[0][1:] == ep.start[:2] and way[-1][0] == period
    k, reached = 0, False
    for (t0, x0, y0), (t1, x1, y1) in zip(way[:-1], way[1:], strict=True):
        assert abs(x1 - x0) + abs(y1 - y0) <= 100.0 + 1e-6  # one lattice step or none per unit
        for t in range(t0 + 1, t1 + 1):
            f = (t - t0) / (t1 - t0)
            x, y = x0 + f * (x1 - x0), y0 + f * (y1 - y0)
            assert not disc_hits(occ, h, w, CELL, x, y, 150.0)
            assert all(np.hypot(x - dx, y - dy) >= 150 + r for dx, dy, r in discs)
            assert all(np.hypot(x - m[0], y - m[1]) >= 150 + m[4] for m in movers)  # before their step ...
            step_movers(movers, occ, CELL, discs, x, y, 150.0, PERIOD_S)
            assert all(np.hypot(x - m[0], y - m[1]) >= 150 + m[4] for m in movers)  # ... and after it
            assert np.allclose(movers[:, :2], free_walk[t, :, :2])  # none stood or turned for the robot
            while np.hypot(x - wps[k, 0], y - wps[k, 1]) <= GOAL_TOL_MM and not reached:
                reached = k == len(wps) - 1
                k += 0 if reached else 1
    assert reached and np.hypot(way[-1][1] - wps[-1, 0], way[-1][2] - wps[-1, 1]) <= GOAL_TOL_MM


def test_the_way_found_drives_clear_of_everything_and_no_mover_reacts_to_it() -> None:
    gm = load_map("maze-12x12-s306")
    found = 0
    for yields in (False, True):
        for ep in episodes(gm, 6, 0, 6, 3, movers=MoverStyle(speed=MOVER_SPEED_MM_S, yields=yields)):
            period, way = solve_path(ep, gm, 150, BUDGET_BASE, BUDGET_FACTOR, PERIOD_S)
            assert period == oracle(ep, gm)
            if period >= 0:
                found += 1
                replay(ep, gm, period, way)
    assert found >= 8


def test_bench_ceiling_reports_the_oracle_beside_the_controllers(tmp_path) -> None:
    out = tmp_path / "c.json"
    r = subprocess.run([sys.executable, "-m", "ground_station", "bench", "ceiling", "--map", "maze-12x12-s306",
                        "--obstacles", "6", "--movers", "3", "--no-yield", "--episodes", "2", "--controllers",
                        "seek_local", "--foresight", "2000", "--kinematic", "--workers", "1", "--json", str(out),
                        "--draw",
                        str(tmp_path / "d")], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "oracle (privileged)" in r.stdout and "oracle seeing 2000 mm" in r.stdout and "seek_local" in r.stdout
    res = json.loads(out.read_text())
    rows = res["episodes"]
    assert [row["index"] for row in rows] == [0, 1]
    solved = sum(row["oracle_s"] is not None for row in rows)
    assert res["oracle"]["solved"] == solved == res["per_map"]["maze-12x12-s306"]["oracle"]
    won = sum(row["seek_local"] == "success" for row in rows)
    s = res["seek_local"]
    assert round(s["success_rate"] * 2) == won
    assert s["failed_oracle_solved"] + s["failed_oracle_not"] == 2 - won
    # --foresight: the limited oracle's outcome and time per episode, its count per map and overall
    seen = [row["seen"] for row in rows]
    assert res["seen"]["right"] == seen.count("success") == res["per_map"]["maze-12x12-s306"]["seen"]
    assert all((row["seen_s"] is not None) == (row["seen"] == "success") for row in rows)
    assert s["failed_seen_solved"] == sum(row["seek_local"] != "success" and row["seen"] == "success" for row in rows)
    assert s["paired_with_seen"]["a_only"] == sum(row["seek_local"] == "success" and row["seen"] != "success"
                                                  for row in rows)
    both = [row for row in rows if row["seen_s"] is not None and row["oracle_s"] is not None]
    assert res["seen"]["both_finished"] == len(both)
    assert res["seen"]["as_quick_as_oracle"] == sum(row["seen_s"] == row["oracle_s"] for row in both)
    # --kinematic: the robot's-moves oracle's time per episode, never quicker than the oracle's
    assert "oracle, robot's moves" in r.stdout
    kin = [row["kinematic_s"] for row in rows]
    assert res["kinematic"]["right"] == sum(k is not None for k in kin) == res["per_map"]["maze-12x12-s306"]["kinematic"]
    assert all(row["oracle_s"] is not None and k >= row["oracle_s"] for row, k in zip(rows, kin, strict=True) if k is not None)
    assert s["paired_with_kinematic"]["a_only"] == sum(row["seek_local"] == "success" and row["kinematic_s"] is None
                                                       for row in rows)
    # --draw: one PNG per episode seek_local got wrong and the oracle right (none, maybe: the drawing
    # itself is checked below)
    folder = tmp_path / "d"
    drawn = sorted(p.name for p in folder.iterdir()) if folder.exists() else []
    assert drawn == [f"maze-12x12-s306-{row['index']}.png" for row in rows
                     if row["seek_local"] != "success" and row["oracle_s"] is not None]
    assert all((folder / n).read_bytes()[:8] == PNG for n in drawn)


def test_a_drawing_shows_the_controllers_drive_beside_the_oracles_way() -> None:
    from firmware_py.policy import load_policy
    from firmware_py.shipped_policies import resolve_policy_spec
    from ground_station.lab.bench.ceiling import draw
    from ground_station.lab.nav.controllers import standard_controllers

    gm = load_map("maze-12x12-s306")
    ep = episodes(gm, 1, 0, 6, 3, movers=MoverStyle(speed=MOVER_SPEED_MM_S, yields=False))[0]
    ctrl = standard_controllers(load_policy(str(resolve_policy_spec("policies:sector"))), ("seek_local",))[0]
    png = draw(ep, gm, ctrl, {"map": gm.name, "index": 0})
    assert png[:8] == PNG and len(png) > 10_000  # two panels of a maze, not an empty figure


def test_on_blocked_passages_the_oracle_finds_no_way_where_the_label_says_none(tmp_path) -> None:
    # the label "no detour" is the scenario's own search (a disc the robot's bare disc cannot pass, on the
    # known map); the oracle searches with the discs and the movers and three times the budget: it must
    # agree, and pass where a detour exists
    out = tmp_path / "b.json"
    r = subprocess.run([sys.executable, "-m", "ground_station", "bench", "ceiling", "--blocked", "both", "--map",
                        "maze-12x12-s306", "--episodes", "6", "--controllers", "", "--budget-scale", "3",
                        "--workers", "1", "--json", str(out)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    res = json.loads(out.read_text())
    rows = res["episodes"]
    assert [row["detour"] for row in rows] == [True, False] * 3
    assert all(row["oracle_s"] is None for row in rows if not row["detour"])
    assert res["oracle"]["found_without_detour"] == 0
    assert res["oracle"]["solved"] == sum(row["oracle_s"] is not None for row in rows) >= 1


def test_bench_ceiling_names_a_bad_budget_scale() -> None:
    r = subprocess.run([sys.executable, "-m", "ground_station", "bench", "ceiling", "--map", "paper10",
                        "--budget-scale", "0"], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and "--budget-scale 0" in r.stderr and "Traceback" not in r.stderr


def test_bench_ceiling_names_a_bad_foresight() -> None:
    r = subprocess.run([sys.executable, "-m", "ground_station", "bench", "ceiling", "--map", "paper10",
                        "--foresight", "-5"], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and "--foresight -5" in r.stderr and "Traceback" not in r.stderr


# --- the oracle limited to what the robot has seen ----------------------------------------------

def seen(ep: Episode, gm: GridMap, see_mm: float) -> tuple[str, int]:
    return solve_seen(ep, gm, 150, BUDGET_BASE, BUDGET_FACTOR, PERIOD_S, see_mm)


def test_the_robot_sees_a_mover_in_reach_and_not_through_a_wall_or_a_disc() -> None:
    gm = CORRIDOR
    occ = gm.occ.astype(np.uint8)
    none = np.zeros((0, 3))
    rx, ry = centre(gm, 9, 1)  # at the door
    assert sees(occ, CELL, none, rx, ry, *centre(gm, 5, 1), 2500.0)  # along the corridor, 2 m off
    assert not sees(occ, CELL, none, rx, ry, *centre(gm, 5, 1), 1900.0)  # beyond its reach
    assert not sees(occ, CELL, none, *centre(gm, 9, 3), *centre(gm, 5, 1), 5000.0)  # the shaft's wall between
    disc = np.array([[centre(gm, 7, 1)[0], centre(gm, 7, 1)[1], 100.0]])
    assert not sees(occ, CELL, disc, rx, ry, *centre(gm, 5, 1), 2500.0)  # a disc on the line


# an open room; the robot crosses it along row 4 while two movers that do not give way cross its way
OPEN = grid(["@" * 14] + ["@" + "." * 12 + "@"] * 8 + ["@" * 14])


def crossing_episode() -> Episode:
    (ax, ay), (bx, by) = centre(OPEN, 6, 1), centre(OPEN, 9, 8)
    return episode(OPEN, centre(OPEN, 1, 4), [centre(OPEN, 12, 4)],
                   ((ax, ay, 0.0, -400.0, 150.0, 0.0), (bx, by, 0.0, 500.0, 150.0, 0.0)))


def test_seeing_every_mover_the_limited_oracle_drives_the_oracles_time() -> None:
    # nothing to see: the same search, the same time
    x, y = centre(ROOM, 1, 2)
    for wps in ([(x + 1000, y)], [(x, y + 400), (x + 1000, y)]):
        assert seen(episode(ROOM, (x, y), wps), ROOM, 2000.0) == ("success", oracle(episode(ROOM, (x, y), wps), ROOM))
    # both movers in sight from the start (an open room, 2 m or all of it): each tracked from its sightings,
    # re-planned each second as it drives, it arrives when the oracle that knew their walks does
    ep = crossing_episode()
    best = oracle(ep, OPEN)
    assert best > 0
    assert seen(ep, OPEN, 100_000.0) == ("success", best)
    assert seen(ep, OPEN, 2000.0) == ("success", best)


def test_a_mover_standing_at_the_robot_is_let_by_and_one_it_cannot_let_by_is_a_stand_off() -> None:
    # seeing 300 mm beyond the bodies, the robot finds the mover coming down at it on its way: the mover
    # (it does not give way) stands at its body, the search finds no way that keeps clear of it, so the
    # robot backs off: a body's width aside (along the mover's way it would follow), and the mover walks on
    ep = crossing_episode()
    assert oracle(ep, OPEN) > 0 and seen(ep, OPEN, 300.0)[0] == "success"
    occ = np.ascontiguousarray(OPEN.occ, dtype=np.uint8)
    down = np.array([[4750.0, 3050.0, 0.0, -500.0, 150.0, 0.0]])  # 316 mm from the robot's centre, coming
    assert _back_off(occ, CELL, 150, np.zeros((0, 3)), down, 4650.0, 2750.0, PERIOD_S) == (4550.0, 2750.0)
    # in the dead end of the one-cell corridor with a mover walking in: no way aside or back, the mover
    # stands at it to the end of the budget (the oracle that knew its walk finds no way either)
    start, (mx, my) = centre(CORRIDOR, 1, 1), centre(CORRIDOR, 5, 1)
    pinned = episode(CORRIDOR, start, [centre(CORRIDOR, 9, 3)], ((mx, my, -300.0, 0.0, 150.0, 0.0),))
    assert oracle(pinned, CORRIDOR) == -1
    assert seen(pinned, CORRIDOR, 2000.0) == ("stand-off", budget_of(pinned))
    # no way at all and no mover near: a plain timeout
    walled = grid(["@@@@@@@", "@..@..@", "@..@..@", "@@@@@@@"])
    shut = episode(walled, centre(walled, 1, 1), [centre(walled, 5, 2)])
    assert oracle(shut, walled) == -1
    assert seen(shut, walled, 2000.0) == ("timeout", budget_of(shut))


def budget_of(ep: Episode) -> int:
    """The episode's period budget, rounded down to whole time units (where `solve_seen` stops)."""
    from ground_station.lab.nav.oracle import UNIT_PERIODS
    from ground_station.lab.nav.planned import budget_periods

    *_, plan_len = rollout_arrays(ep, True)
    return int(budget_periods(plan_len, BUDGET_BASE, BUDGET_FACTOR)) // UNIT_PERIODS * UNIT_PERIODS
