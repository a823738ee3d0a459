"""Blocked-passage scenarios (ground_station/lab/nav/scenario.py `blocked_episodes`,
`qnav bench nav --blocked`): the blocking disc meets the documented
conditions a-e, checked here on a configuration-space raster computed in this
file (numpy, not the module's kernel) with `octile_distances`; the label is
right both ways; episodes are seeded and round-trip through JSON; `summarise`
counts "no route" apart; the CLI runs end to end and skips a map without such
an episode."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from firmware_py import robot_spec
from ground_station.lab.nav import scenario as sc
from ground_station.lab.nav.episodes import summarise
from ground_station.maps import GridMap, MapError, load_map, octile_distances
from ground_station.maps.planner import plan_waypoints
from ground_station.nav import obstacles as ob
from tests.support.cli import run_qnav as _qnav

STEP = 50.0  # raster step, mm
R = robot_spec.ROBOT_RADIUS_MM


def _raster(gm: GridMap, discs: list, margin: float) -> np.ndarray:
    """Points ((i + 0.5) * STEP) where the robot's disc grown by `margin` touches no obstacle cell,
    the border or a disc; row 0 = south."""
    cell = gm.cell_size_m * 1000.0
    h, w = gm.occ.shape
    clear = R + margin
    xs = (np.arange(int(w * cell / STEP)) + 0.5) * STEP
    ys = (np.arange(int(h * cell / STEP)) + 0.5) * STEP
    x, y = np.meshgrid(xs, ys)
    ok = (x >= clear) & (y >= clear) & (x <= w * cell - clear) & (y <= h * cell - clear)
    for row, col in np.argwhere(gm.occ):
        ylo = (h - row - 1) * cell
        dx = np.clip(x, col * cell, (col + 1) * cell) - x
        dy = np.clip(y, ylo, ylo + cell) - y
        ok &= dx * dx + dy * dy >= clear * clear
    for cx, cy, r in discs:
        ok &= (x - cx) ** 2 + (y - cy) ** 2 >= (clear + r) ** 2
    return ok


def _snap(free: np.ndarray, p: tuple[float, float]) -> tuple[int, int]:
    """The free raster point nearest to p (within 150 mm), as (ix, iy)."""
    iy, ix = np.nonzero(free)
    d = ((ix + 0.5) * STEP - p[0]) ** 2 + ((iy + 0.5) * STEP - p[1]) ** 2
    k = int(np.argmin(d))
    assert d[k] <= 150.0 ** 2, f"no free raster point near {p}"
    return int(ix[k]), int(iy[k])


def _legs_connected(gm: GridMap, points: list, discs: list, margin: float) -> list[bool]:
    free = _raster(gm, discs, margin)
    out = []
    for a, b in zip(points[:-1], points[1:], strict=True):
        (ax, ay), (bx, by) = _snap(free, a), _snap(free, b)
        out.append(bool(np.isfinite(octile_distances(~free, bx, by)[ay, ax])))
    return out


def _disc_in_free_space(gm: GridMap, x: float, y: float, r: float) -> bool:
    cell = gm.cell_size_m * 1000.0
    h, w = gm.occ.shape
    if not (r <= x <= w * cell - r and r <= y <= h * cell - r):
        return False
    for row, col in np.argwhere(gm.occ):
        ylo = (h - row - 1) * cell
        px, py = min(max(x, col * cell), (col + 1) * cell), min(max(y, ylo), ylo + cell)
        if math.hypot(x - px, y - py) < r:
            return False
    return True


def _check_blocking(gm: GridMap, ep: sc.Episode) -> bool:
    """Conditions a-d of the module docstring, checked independently; returns the label."""
    assert ep.blocked is not None
    disc = tuple(ep.blocked["disc"])
    assert tuple(ep.discs[0]) == disc  # the twin and the pymunk plant see it as an ordinary disc
    x, y, r = disc
    assert sc.BLOCK_RADIUS_MM[0] <= r <= sc.BLOCK_RADIUS_MM[1]
    start = ep.start[:2]
    points = [start, *ep.waypoints]
    assert _disc_in_free_space(gm, x, y, r)  # a.
    for px, py in points:  # b.
        assert math.hypot(px - x, py - y) >= r + R + ob.WAYPOINT_CLEAR_MM
    assert all(_legs_connected(gm, points, [], ob.CSPACE_MARGIN_MM))  # the route is passable without it
    assert ob.detourable(gm, start, ep.waypoints, [])
    assert not ob.detourable(gm, start, ep.waypoints, [disc])  # c. it blocks the route locally
    with_margin = _legs_connected(gm, points, [disc], ob.CSPACE_MARGIN_MM)
    bare = _legs_connected(gm, points, [disc], 0.0)
    if ep.blocked["detour"]:  # d. connected elsewhere with margin
        assert all(with_margin)
    else:  # d. not even the bare robot gets past
        assert not all(bare)
        assert not all(with_margin)
    return bool(ep.blocked["detour"])


def _grid(rows: list[str], name: str) -> GridMap:
    return GridMap(name=name, occ=np.array([[c == "#" for c in r] for r in rows]))


ONE_CORRIDOR = _grid(["############", "#...####...#", "#..........#", "#...####...#", "#...####...#",
                      "############"], "one-corridor")
TWO_CORRIDORS = _grid(["############", "#...####...#", "#..........#", "#...####...#", "#..........#",
                       "############"], "two-corridors")


@pytest.mark.parametrize(("gm", "label"), [(ONE_CORRIDOR, False), (TWO_CORRIDORS, True)],
                         ids=["one corridor: no detour", "two corridors: detour"])
def test_a_disc_in_a_corridor_is_labelled_by_the_route_elsewhere(gm, label):
    """Two rooms joined by one corridor (no route around a disc in it) or by two (a route through the
    other, 2 km longer than the blocked one: not a local detour)."""
    wps = [(float(x), float(y)) for x, y in plan_waypoints(gm, (1, 2), (10, 2))]
    start = (750.0, 1750.0)
    for seed in range(5):
        got = sc.place_blocking_disc(gm, start, wps, np.random.default_rng(seed), None)
        assert got is not None
        disc, detour = got
        assert detour is label
        assert 1500.0 < disc[0] < 4500.0  # in the corridor (x 2000-4000 mm) or its mouth: where it is narrow
        ep = sc.Episode(map=gm.name, start=(*start, 0.0), goal=(10, 2), goal_mm=wps[-1], waypoints=wps,
                        discs=[disc], blocked={"disc": list(disc), "detour": detour})
        assert _check_blocking(gm, ep) is label
        assert sc.place_blocking_disc(gm, start, wps, np.random.default_rng(seed), not label) is None


@pytest.mark.parametrize(("name", "want"), [("rooms-16x16-s1", True), ("rooms-16x16-s1", False),
                                            ("maze-16x16-s1", None), ("trap-16x16-s1", False),
                                            ("random-16x16-s1", True)])
def test_every_blocking_disc_meets_the_definition(name, want):
    gm = load_map(name)
    eps = sc.blocked_episodes(gm, 6, 2, want)
    labels = [_check_blocking(gm, e) for e in eps]
    assert len(eps) == 6
    if want is not None:
        assert labels == [want] * 6
    else:  # the maze has passages of both kinds
        assert set(labels) == {True, False}


def test_a_map_without_such_a_passage_says_so():
    # paper10: every passage on a planned route has a way round it (no dead-end room behind one door)
    with pytest.raises(MapError, match="paper10.*no detour"):
        sc.blocked_episodes(load_map("paper10"), 1, 0, False)
    assert len(sc.blocked_episodes(load_map("paper10"), 2, 0, True)) == 2


def test_blocked_episodes_are_seeded_and_round_trip_through_json():
    gm = load_map("rooms-16x16-s1")
    a = sc.blocked_episodes(gm, 5, 3, None, k=2, m=1)
    assert [e.to_json() for e in a] == [e.to_json() for e in sc.blocked_episodes(gm, 5, 3, None, k=2, m=1)]
    assert [e.to_json() for e in a[:3]] == [e.to_json() for e in sc.blocked_episodes(gm, 3, 3, None, k=2, m=1)]
    assert [e.to_json() for e in a] != [e.to_json() for e in sc.blocked_episodes(gm, 5, 4, None, k=2, m=1)]
    back = [sc.Episode.from_json(json.loads(json.dumps(e.to_json()))) for e in a]
    assert [e.to_json() for e in back] == [e.to_json() for e in a]
    assert all(e.blocked is not None and e.blocked == b.blocked for e, b in zip(a, back, strict=True))
    old = a[0].to_json()
    del old["blocked"]  # JSON written before the field existed
    assert sc.Episode.from_json(old).blocked is None
    assert sc.episodes(gm, 2, 3, 1, 0)[0].blocked is None  # the ordinary scenarios have none


def test_extra_discs_stay_detourable_and_keep_the_label():
    gm = load_map("rooms-16x16-s1")
    eps = sc.blocked_episodes(gm, 8, 5, True, k=3)
    assert sum(len(e.discs) - 1 for e in eps) >= 4  # extras are placed...
    for e in eps:
        block, extras = e.discs[0], e.discs[1:]
        points = [e.start[:2], *e.waypoints]
        assert ob.detourable(gm, e.start[:2], e.waypoints, extras)  # ...against the map alone
        for x, y, r in extras:
            assert math.hypot(x - block[0], y - block[1]) >= r + block[2]  # not overlapping the block
        assert all(_legs_connected(gm, points, e.discs, ob.CSPACE_MARGIN_MM))  # and a route stays open


def test_extra_discs_that_overlap_the_block_or_close_the_detour_are_dropped(monkeypatch):
    """Extras are placed against the map alone; on the two-corridor map one that sits on the blocking
    disc, or closes the other corridor (the detour), is not kept, a harmless one is."""
    blocks: list = []
    real = sc.place_blocking_disc

    def spy(*a, **kw):
        got = real(*a, **kw)
        blocks.append(got)
        return got

    def extras(gm, start, wps, k, rng):
        x, y, r = blocks[-1][0]
        other = 750.0 if y > 1250.0 else 1750.0  # the corridor the blocking disc is not in
        return [(x + 20.0, y, 150.0), (3000.0, other, 240.0), (700.0, 2200.0, 120.0)][:k]

    monkeypatch.setattr(sc, "place_blocking_disc", spy)
    monkeypatch.setattr(sc, "place_discs", extras)
    for e in sc.blocked_episodes(TWO_CORRIDORS, 3, 0, True, k=3):
        assert e.blocked is not None and e.blocked["detour"]
        assert e.discs == [tuple(e.blocked["disc"]), (700.0, 2200.0, 120.0)]
        assert all(_legs_connected(TWO_CORRIDORS, [e.start[:2], *e.waypoints], e.discs, ob.CSPACE_MARGIN_MM))

def test_summarise_counts_no_route_apart():
    def row(outcome: str, detour: bool | None) -> dict:
        r = {"outcome": outcome, "success": outcome == "success", "collision": outcome == "collision",
             "path_ratio": 1.1 if outcome == "success" else None, "time_s": 10.0, "near_miss_periods": 0}
        return r if detour is None else {**r, "blocked": {"detour": detour}}

    rows = ([row("success", True)] * 2 + [row("no_route", True)] + [row("no_route", False)] * 3
            + [row("collision", False)])
    s = summarise(rows)
    assert s["episodes"] == 7 and s["success_rate"] == 2 / 7
    assert s["no_route_rate"] == 4 / 7 and s["outcomes"]["no_route"] == 4
    d, n = s["blocked"]["detour"], s["blocked"]["none"]
    assert d["episodes"] == 3 and d["success_rate"] == 2 / 3 and d["no_route_rate"] == 1 / 3
    assert n["episodes"] == 4 and n["no_route_reported"] == 3 / 4 and n["collision_rate"] == 1 / 4
    assert n["no_route_reported_ci95"][0] < 0.75 < n["no_route_reported_ci95"][1]
    plain = summarise([row("success", None), row("timeout", None)])
    assert "blocked" not in plain and plain["no_route_rate"] == 0.0


def test_bench_nav_blocked_end_to_end(tmp_path):
    js = tmp_path / "nav.json"
    code, out, err = _qnav("bench", "nav", "--blocked", "detour", "--episodes", "2", "--map", "rooms-16x16-s1",
                           "--controllers", "seek", "--movers", "0", "--json", str(js))
    assert code == 0, out + err
    d = json.loads(js.read_text())
    assert d["scenario"]["blocked"] == "detour" and d["scenario"]["obstacles"] == 0
    assert d["scenario"]["discs_placed_mean"] == 1.0  # the blocking disc alone
    assert d["seek"]["episodes"] == 2 and d["seek"]["blocked"]["detour"]["episodes"] == 2
    assert d["seek"]["blocked"]["none"]["episodes"] == 0 and "no_route_rate" in d["seek"]
    assert "no-route" in out and "twin seek" in out


def test_bench_nav_blocked_skips_a_map_without_such_an_episode(tmp_path):
    js = tmp_path / "nav.json"
    code, out, err = _qnav("bench", "nav", "--blocked", "both", "--episodes", "3", "--map", "paper10",
                           "--map", "maze-16x16-s1", "--controllers", "seek", "--movers", "0", "--json", str(js))
    assert code == 0, out + err
    skip = [ln for ln in err.splitlines() if "skipping" in ln]
    assert len(skip) == 1 and "paper10" in skip[0] and "no detour" in skip[0]
    d = json.loads(js.read_text())
    assert d["scenario"]["maps"] == ["maze-16x16-s1"] and list(d["scenario"]["maps_skipped"]) == ["paper10"]
    b = d["seek"]["blocked"]
    assert b["detour"]["episodes"] == 2 and b["none"]["episodes"] == 1  # both: 2 + 1 of 3, interleaved
    code, out, err = _qnav("bench", "nav", "--blocked", "none", "--episodes", "2", "--map", "paper10",
                           "--controllers", "seek")
    assert code == 2 and "paper10" in out + err


def test_the_twin_lets_the_recoveries_run_to_no_route_without_the_loop_rule_cutting_them():
    """rooms-16x16-s1, a passage closed with no way round (seed 0, 3 discs + 2 movers, episode 3): the
    robot's recoveries (waits of 2, 4, 6 s, back-offs, moving-scene rounds that do not count) stand
    it still for longer than the loop rule's 20 s without progress (34 s). Periods the planner holds the robot
    still or backs it off on purpose are not counted toward that rule (the budget still bounds them),
    so the episode ends as the robot ends it: NO_ROUTE, not LOOP; and the robot stood for > 20 s."""
    from firmware_py.kinds.sector.recoveries import PlannedTarget
    from firmware_py.policy import load_policy
    from firmware_py.shipped_policies import shipped_policy
    from ground_station.lab.nav import planned
    from ground_station.lab.nav.controllers import standard_controllers
    from ground_station.lab.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS
    from ground_station.lab.nav.obstacle_twin import NO_ROUTE

    gm = load_map("rooms-16x16-s1")
    ep = sc.blocked_episodes(gm, 4, 0, False, k=3, m=2)[3]
    ctrl = standard_controllers(load_policy(shipped_policy("sector")), ("learnt",))[0]
    still = []
    target = PlannedTarget.target

    def counting(self, now_us, x, y, waypoint, memory):  # type: ignore[no-untyped-def]
        out = target(self, now_us, x, y, waypoint, memory)
        still.append(out[2] == 0)
        return out

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(PlannedTarget, "target", counting)
        outcome, *_ = planned.rollout(ep, gm, ctrl, BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS)
    assert outcome == NO_ROUTE
    assert sum(still) > STALL_STEPS  # more than the loop rule's periods standing in recoveries
