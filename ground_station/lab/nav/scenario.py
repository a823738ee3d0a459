"""Navigation scenarios: a map, an episode, and obstacles the planner does not know.

The one definition of a scenario episode, used by the twin's rollouts
(`ground_station.lab.nav.obstacle_twin`), the pymunk plant
(`sim_bridge.obstacles.ObstacleLayer`) and `qnav bench nav`. An `Episode`
is plain data (JSON round trip): start pose, goal, the planner's waypoints on
the known map, static discs and movers; `make_episode(gridmap, start, goal, heading, k, m, rng)` builds one
from a seeded `numpy.random.Generator`.

The static discs and movers in an episode are those of
`ground_station.nav.obstacles` (`place_discs`, `place_movers`: conditions 1.-3.
of a **detourable** set, in that module's docstring); `Episode.discs` says how
many were placed.

**Blocked passages** (`blocked_episodes`, `qnav bench nav --blocked`): every
episode has one disc that closes a narrow passage (a door, a one-cell
corridor or aisle) on the planned route; it is the first of `Episode.discs`
and `Episode.blocked` = {"disc": [x, y, r], "detour": bool} labels it. The
centre is drawn on the waypoint polyline between 10 % and 90 % of its length,
moved sideways by up to `BLOCK_LATERAL_MM`, radius uniform in
`BLOCK_RADIUS_MM`; a candidate is kept only if

a. the disc lies in free space (as 1. above);
b. the start and every waypoint keep >= robot radius + `WAYPOINT_CLEAR_MM`
   from its surface (as 2.: the robot never needs to skip a mission item);
c. it blocks the route locally: the set is not detourable (3. fails: some
   leg is disconnected, or its detour is more than `DETOUR_MAX_MM` longer);
d. its label is unambiguous. `detour` = True: on the configuration-space
   raster of 3. (robot radius + `CSPACE_MARGIN_MM`) with the disc, every leg
   start -> w0 -> ... -> goal is still connected: a route exists elsewhere,
   with margin (by c. it is more than `DETOUR_MAX_MM` longer, or the disc
   would not block). `detour` = False: some leg is disconnected even on the
   raster with the robot's bare radius (margin `BLOCK_BARE_MARGIN_MM` = 0):
   the robot's own disc cannot get past anywhere, so the goal cannot be
   reached and "no route" is the right answer. Candidates between the two
   (connected at margin 0, not at `CSPACE_MARGIN_MM`) are dropped;
e. with `want_detour` given, the label is the one asked for.

The route without the disc must be connected at `CSPACE_MARGIN_MM` (else
there is nothing to block). Labels are about the known map and the discs
(movers aside). Extra detourable discs (`k`) are placed against the map
without the blocking disc and kept only if they do not overlap it and, for
`detour` = True, leave every leg connected. A map may have no passage of a
label: none with a route around it (one door between two rooms, a
tree-shaped maze) or none without (paper10: every passage on a route has a
way round, no dead end behind it); `blocked_episodes` then raises MapError
naming the map and the label.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from itertools import zip_longest

import numpy as np

from firmware_py import robot_spec
from ground_station.maps import GridMap, MapError, bfs_distances, octile_distances
from ground_station.maps.planner import plan_waypoints
from ground_station.nav.obstacles import (
    CSPACE_MARGIN_MM,
    DETOUR_MAX_MM,
    MOVER_SPEED_MM_S,
    RASTER_MM,
    WAYPOINT_CLEAR_MM,
    cspace,
    disc_blocked,
    place_discs,
    place_movers,
    point_along,
    raster_index,
)
from sim_bridge.obstacles import mover_array

BLOCK_SPAN = (0.10, 0.90)  # share of the planned route where a blocking disc's centre is drawn
BLOCK_LATERAL_MM = 100.0
BLOCK_RADIUS_MM = (150.0, 260.0)
BLOCK_BARE_MARGIN_MM = 0.0  # the "no detour" label: not even the robot's bare disc gets past
BLOCK_TRIES = 40


@dataclass(frozen=True)
class MoverStyle:
    """How a scenario's movers walk: speed range (mm/s) and whether they step aside for the robot."""

    speed: tuple[float, float] = MOVER_SPEED_MM_S
    yields: bool = True


@dataclass
class Episode:
    """One scenario episode, all lengths mm, angles rad (world frame of robot_spec)."""

    map: str
    start: tuple[float, float, float]  # x, y, heading
    goal: tuple[int, int]  # (col, row)
    goal_mm: tuple[float, float]
    waypoints: list[tuple[float, float]]  # the planner's, last = the goal's centre
    discs: list[tuple[float, float, float]] = field(default_factory=list)  # x, y, r
    # x, y, vx, vy, r, yields (1: steps aside for the robot; 0: walks its line, stops only on contact)
    movers: list[tuple[float, ...]] = field(default_factory=list)
    seed: int = 0
    # blocked-passage episodes: {"disc": [x, y, r] (also ep.discs[0]), "detour": a route exists elsewhere}
    blocked: dict | None = None

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> Episode:
        return cls(map=str(d["map"]), start=tuple(d["start"]), goal=tuple(d["goal"]),  # type: ignore[arg-type]
                   goal_mm=tuple(d["goal_mm"]), waypoints=[tuple(p) for p in d["waypoints"]],  # type: ignore[misc]
                   discs=[tuple(p) for p in d.get("discs", [])],  # type: ignore[misc]
                   movers=[tuple(p) for p in d.get("movers", [])], seed=int(d.get("seed", 0)),  # type: ignore[misc]
                   blocked=_blocked_json(d.get("blocked")))


def _blocked_json(b: dict | None) -> dict | None:
    if b is None:
        return None
    return {"disc": [float(v) for v in b["disc"]], "detour": bool(b["detour"])}


def make_episode(gridmap: GridMap, start: tuple[int, int], goal: tuple[int, int], heading: float,
                 k: int = 0, m: int = 0, seed: int = 0, plan_kw: dict | None = None,
                 movers: MoverStyle | None = None) -> Episode:
    """A seeded scenario episode from start cell (its centre) to goal cell with
    up to k static discs and m movers. Raises MapError if the planner finds no path."""
    rng = np.random.default_rng(seed)
    cell = gridmap.cell_size_m * 1000.0
    h = gridmap.height
    sx, sy = (start[0] + 0.5) * cell, (h - start[1] - 0.5) * cell
    wps = [(float(x), float(y)) for x, y in plan_waypoints(gridmap, start, goal, **(plan_kw or {}))]
    discs = place_discs(gridmap, (sx, sy), wps, k, rng)
    style = movers or MoverStyle()
    walkers = place_movers(gridmap, (sx, sy), discs, m, rng, style.speed, style.yields)
    gx, gy = (goal[0] + 0.5) * cell, (h - goal[1] - 0.5) * cell
    return Episode(map=gridmap.name, start=(sx, sy, float(heading)), goal=(int(goal[0]), int(goal[1])),
                   goal_mm=(gx, gy), waypoints=wps, discs=discs, movers=walkers, seed=int(seed))


def _draw_pair(rng: np.random.Generator, cells: list, min_cells: float
               ) -> tuple[tuple[int, int], tuple[int, int], float] | None:
    """One draw of (start cell, goal cell, heading) as every episode list makes it (None: the cells
    are nearer than min_cells in a straight line; the heading is then not drawn)."""
    a, b = rng.choice(len(cells), size=2, replace=False)
    s, g = cells[int(a)], cells[int(b)]
    if math.hypot(s[0] - g[0], s[1] - g[1]) < min_cells:
        return None
    return s, g, float(rng.uniform(-math.pi, math.pi))


def for_body(gridmap: GridMap, ep: Episode, radius_mm: float, plan_kw: dict | None = None) -> Episode:
    """The same episode (start, goal, discs, movers, seed) with the planner's waypoints for a robot
    of body radius `radius_mm` (a profile's): what `qnav mission upload --plan --profile` sends it.
    Raises MapError if its planner finds no path."""
    cell = gridmap.cell_size_m * 1000.0
    start = (int(ep.start[0] // cell), gridmap.height - 1 - int(ep.start[1] // cell))
    wps = plan_waypoints(gridmap, start, ep.goal, **{**(plan_kw or {}), "radius_mm": radius_mm})
    return replace(ep, waypoints=[(float(x), float(y)) for x, y in wps])


def episodes(gridmap: GridMap, n: int, seed: int, k: int, m: int, plan_kw: dict | None = None,
             min_cells: float = 3.0, movers: MoverStyle | None = None) -> list[Episode]:
    """n seeded episodes on gridmap: random connected (start, goal) free cells
    at least `min_cells` cells apart (straight line), random heading; episode
    i uses seed (seed, i) for its obstacles, so a list is reproducible and
    its prefixes agree."""
    rng = np.random.default_rng(seed)
    cells = gridmap.free_cells()
    out: list[Episode] = []
    attempts = 0
    while len(out) < n:
        attempts += 1
        if attempts > 50 * n + 100:
            raise MapError(f"map {gridmap.name}: cannot draw {n} connected start/goal pairs")
        pair = _draw_pair(rng, cells, min_cells)
        if pair is None:
            continue
        s, g, heading = pair
        try:
            ep = make_episode(gridmap, s, g, heading, k, m, seed=int(seed) * 1_000_003 + len(out), plan_kw=plan_kw,
                              movers=movers)
        except MapError:
            continue
        out.append(ep)
    return out


# --- blocked passages --------------------------------------------------------------

_FREE_CACHE: dict[tuple, np.ndarray] = {}


def _free_raster(gridmap: GridMap, margin: float) -> np.ndarray:
    """The map's configuration-space raster without discs (robot radius + margin), cached per map."""
    key = (gridmap.occ.shape, gridmap.occ.tobytes(), float(gridmap.cell_size_m), float(margin))
    free = _FREE_CACHE.get(key)
    if free is None:
        if len(_FREE_CACHE) >= 32:
            _FREE_CACHE.clear()
        occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
        free = cspace(occ, gridmap.cell_size_m * 1000.0, np.zeros((0, 3)), RASTER_MM,
                       robot_spec.ROBOT_RADIUS_MM + margin)
        _FREE_CACHE[key] = free
    return free


def _close_disc(free: np.ndarray, disc: tuple[float, float, float], clear: float) -> np.ndarray:
    """`free` with the raster points a disc closes for a robot disc of radius `clear` removed:
    the same test as `cspace`'s disc loop, so the result equals `cspace` with the disc."""
    x, y, r = disc
    d = clear + r
    ny, nx = free.shape
    ix0, ix1 = max(0, int((x - d) // RASTER_MM) - 1), min(nx, int((x + d) // RASTER_MM) + 2)
    iy0, iy1 = max(0, int((y - d) // RASTER_MM) - 1), min(ny, int((y + d) // RASTER_MM) + 2)
    out = free.copy()
    if ix0 >= ix1 or iy0 >= iy1:
        return out
    xs = (np.arange(ix0, ix1) + 0.5) * RASTER_MM
    ys = (np.arange(iy0, iy1) + 0.5) * RASTER_MM
    hit = (xs[None, :] - x) ** 2 + (ys[:, None] - y) ** 2 < d * d
    out[iy0:iy1, ix0:ix1] &= ~hit
    return out


def _all_connected(free: np.ndarray, points: list[tuple[float, float]]) -> bool:
    """Every leg points[i] -> points[i+1] connected on `free` (as `nav.obstacles._raster_legs` finite): all points
    in the first one's component. 4-connected reachability equals 8-connected without corner cutting."""
    idx = [raster_index(free, *p) for p in points]
    dist = bfs_distances(~free, idx[0][0], idx[0][1])
    return all(dist[iy, ix] >= 0 for ix, iy in idx)


class _Route:
    """One planned route (start, then the waypoints) on the map's configuration-space raster
    (robot radius + CSPACE_MARGIN_MM): what every candidate blocking disc of the route shares."""

    def __init__(self, gridmap: GridMap, points: list[tuple[float, float]]) -> None:
        self.gridmap = gridmap
        self.points = points
        self.free = _free_raster(gridmap, CSPACE_MARGIN_MM)
        self.idx = [raster_index(self.free, *p) for p in points]
        self._fields: list[np.ndarray] | None = None

    def fields(self) -> list[np.ndarray]:
        """Octile distance fields (raster steps) from every point without discs, computed once."""
        if self._fields is None:
            self._fields = [octile_distances(~self.free, ix, iy) for ix, iy in self.idx]
        return self._fields

    def base(self) -> list[float]:
        """Leg lengths (mm) without discs: `nav.obstacles._leg_lengths` of the route with no discs."""
        f = self.fields()
        return [float(f[i + 1][iy, ix]) * RASTER_MM for i, (ix, iy) in enumerate(self.idx[:-1])]

    def label(self, disc: tuple[float, float, float], want: bool | None) -> bool | None:
        """Conditions c and d of the module docstring for a disc that passes a and b: True (blocks
        the route, which stays connected elsewhere with margin), False (blocks, not even the bare
        robot gets past) or None (does not block locally, ambiguous, or cannot be labelled `want`)."""
        free = _close_disc(self.free, disc, robot_spec.ROBOT_RADIUS_MM + CSPACE_MARGIN_MM)
        if _all_connected(free, self.points):
            if want is False:
                return None  # connected with margin: a detour or no block, never "no detour"
            # the legs' lengths with the disc (as `nav.obstacles.detourable`), recomputed only where a shortest
            # path without the disc ran through a raster point the disc closes
            f = self.fields()
            base = self.base()
            closed = self.free & ~free
            idx = [raster_index(free, *p) for p in self.points]
            for i in range(len(self.points) - 1):
                if idx[i] == self.idx[i] and idx[i + 1] == self.idx[i + 1]:
                    through = float(np.min((f[i] + f[i + 1])[closed])) if closed.any() else math.inf
                    if through > base[i] / RASTER_MM + 1e-6:
                        continue  # no shortest path used a closed point: the leg is unchanged
                (ax, ay), (bx, by) = idx[i], idx[i + 1]
                leg = float(octile_distances(~free, bx, by)[ay, ax]) * RASTER_MM
                if not leg <= base[i] + DETOUR_MAX_MM:
                    return True
            return None  # detourable: a local detour exists, the disc blocks nothing
        if want is True:
            return None
        bare = _close_disc(_free_raster(self.gridmap, BLOCK_BARE_MARGIN_MM), disc,
                           robot_spec.ROBOT_RADIUS_MM + BLOCK_BARE_MARGIN_MM)
        return None if _all_connected(bare, self.points) else False


def place_blocking_disc(gridmap: GridMap, start: tuple[float, float], waypoints: list[tuple[float, float]],
                        rng: np.random.Generator, want_detour: bool | None
                        ) -> tuple[tuple[float, float, float], bool] | None:
    """A disc that closes a narrow passage on the route start -> waypoints and its label (a route
    exists elsewhere), meeting a-e of the module docstring (e: the label equals `want_detour`
    unless None); None if none of `BLOCK_TRIES` candidates passes."""
    points = [start, *waypoints]
    total = sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(points[:-1], points[1:], strict=True))
    if total <= 0:
        return None
    route = _Route(gridmap, points)
    if not _all_connected(route.free, points):
        return None  # the route itself is not passable with margin: nothing to block
    occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
    cell = gridmap.cell_size_m * 1000.0
    keep = robot_spec.ROBOT_RADIUS_MM + WAYPOINT_CLEAR_MM
    for _ in range(BLOCK_TRIES):
        x, y, ang = point_along(points, float(rng.uniform(*BLOCK_SPAN)) * total)
        off = float(rng.uniform(-BLOCK_LATERAL_MM, BLOCK_LATERAL_MM))
        x, y = x - off * math.sin(ang), y + off * math.cos(ang)
        r = float(rng.uniform(*BLOCK_RADIUS_MM))
        cand = (round(x, 1), round(y, 1), round(r, 1))
        if disc_blocked(occ, cell, *cand):  # a. in free space
            continue
        if any(math.hypot(px - cand[0], py - cand[1]) < cand[2] + keep for px, py in points):  # b.
            continue
        label = route.label(cand, want_detour)  # c. and d. (and e.: None when not the label wanted)
        if label is None or (want_detour is not None and label != want_detour):
            continue
        return cand, label
    return None


def _label_name(want_detour: bool | None) -> str:
    return {True: "with a detour elsewhere", False: "with no detour", None: "(either label)"}[want_detour]


def blocked_episodes(gridmap: GridMap, n: int, seed: int, want_detour: bool | None, k: int = 0, m: int = 0,
                     plan_kw: dict | None = None, min_cells: float = 3.0,
                     movers: MoverStyle | None = None) -> list[Episode]:
    """n seeded blocked-passage episodes on gridmap (module docstring), drawn as `episodes` draws
    them (reproducible, prefixes agree); each has a blocking disc labelled `want_detour` (any label
    if None), then up to k detourable discs and m movers. Raises MapError naming the map and the
    label when 200 n + 200 start/goal draws do not give n, or the first 200 min(n, 20) + 200 give
    none (the map has no such passage: many have no route around theirs)."""
    rng = np.random.default_rng(seed)
    cells = gridmap.free_cells()
    cell = gridmap.cell_size_m * 1000.0
    h = gridmap.height
    style = movers or MoverStyle()
    out: list[Episode] = []
    attempts, limit, limit_none = 0, 200 * n + 200, 200 * min(n, 20) + 200
    while len(out) < n:
        attempts += 1
        if attempts > limit or (not out and attempts > limit_none) or len(cells) < 2:
            raise MapError(f"map {gridmap.name}: only {len(out)} of {n} blocked-passage episodes "
                           f"{_label_name(want_detour)} in {attempts - 1} start/goal draws")
        pair = _draw_pair(rng, cells, min_cells)
        if pair is None:
            continue
        s, g, heading = pair
        try:
            wps = [(float(x), float(y)) for x, y in plan_waypoints(gridmap, s, g, **(plan_kw or {}))]
        except MapError:
            continue
        ep_seed = int(seed) * 1_000_003 + len(out)
        erng = np.random.default_rng(ep_seed)
        sx, sy = (s[0] + 0.5) * cell, (h - s[1] - 0.5) * cell
        found = place_blocking_disc(gridmap, (sx, sy), wps, erng, want_detour)
        if found is None:
            continue
        disc, detour = found
        points = [(sx, sy), *wps]
        discs = [disc]
        for extra in place_discs(gridmap, (sx, sy), wps, k, erng):  # detourable against the map alone
            if math.hypot(extra[0] - disc[0], extra[1] - disc[1]) < extra[2] + disc[2]:
                continue
            if detour:  # and they must not close the route elsewhere
                free = _free_raster(gridmap, CSPACE_MARGIN_MM)
                for d in [*discs, extra]:
                    free = _close_disc(free, d, robot_spec.ROBOT_RADIUS_MM + CSPACE_MARGIN_MM)
                if not _all_connected(free, points):
                    continue
            discs.append(extra)
        walkers = place_movers(gridmap, (sx, sy), discs, m, erng, style.speed, style.yields)
        gx, gy = (g[0] + 0.5) * cell, (h - g[1] - 0.5) * cell
        out.append(Episode(map=gridmap.name, start=(sx, sy, heading), goal=(int(g[0]), int(g[1])),
                           goal_mm=(gx, gy), waypoints=wps, discs=discs, movers=walkers, seed=ep_seed,
                           blocked={"disc": list(disc), "detour": bool(detour)}))
    return out


def blocked_both(gridmap: GridMap, n: int, seed: int, k: int = 0, m: int = 0,
                 movers: MoverStyle | None = None) -> list[Episode]:
    """The benches' `--blocked both`: (n + 1) // 2 episodes with a detour and n // 2 without, the two
    labels interleaved so every prefix is mixed. Raises MapError as `blocked_episodes`."""
    yes = blocked_episodes(gridmap, (n + 1) // 2, seed, True, k=k, m=m, movers=movers)
    no = blocked_episodes(gridmap, n // 2, seed, False, k=k, m=m, movers=movers)
    return [e for pair in zip_longest(yes, no) for e in pair if e is not None]


def rollout_arrays(ep: Episode, guided: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """One episode as the Python-loop rollouts take it: (discs, movers (a copy: they move), waypoints
    (the goal alone when not guided), remaining path after each, planned length from the start
    through the waypoints: the bench kernels' budget basis)."""
    discs = np.asarray(ep.discs, dtype=np.float64).reshape(-1, 3)
    movers = mover_array(ep.movers)  # a copy: they move
    plan = np.asarray(ep.waypoints, dtype=np.float64)
    wps = plan if guided else np.asarray([ep.goal_mm], dtype=np.float64)
    seg = np.hypot(*np.diff(wps, axis=0).T) if len(wps) > 1 else np.zeros(0)
    rem = np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])
    pseg = np.hypot(*np.diff(plan, axis=0).T) if len(plan) > 1 else np.zeros(0)
    plan_len = float(pseg.sum()) + math.hypot(ep.start[0] - plan[0, 0], ep.start[1] - plan[0, 1])
    return discs, movers, wps, rem, plan_len


def episode_arrays(eps: list[Episode], maps: dict[str, GridMap]) -> dict[str, np.ndarray]:
    """Pack episodes (and their maps, by name) into the arrays the twin kernels take."""
    names = list(dict.fromkeys(e.map for e in eps))
    gms = [maps[n] for n in names]
    hmax = max(g.height for g in gms)
    wmax = max(g.width for g in gms)
    occ = np.ones((len(gms), hmax, wmax), dtype=np.uint8)
    dims = np.zeros((len(gms), 2), dtype=np.int64)
    cells = np.zeros(len(gms))
    for i, g in enumerate(gms):
        occ[i, :g.height, :g.width] = g.occ
        dims[i] = (g.height, g.width)
        cells[i] = g.cell_size_m * 1000.0
    n = len(eps)
    kw = max(len(e.waypoints) for e in eps)
    kd = max(1, max(len(e.discs) for e in eps))
    km = max(1, max(len(e.movers) for e in eps))
    a: dict[str, np.ndarray] = {
        "occ": occ, "dims": dims, "cells": cells,
        "map": np.array([names.index(e.map) for e in eps], dtype=np.int64),
        "start": np.array([e.start for e in eps], dtype=np.float64),
        "goal": np.array([e.goal_mm for e in eps], dtype=np.float64),
        "wp": np.zeros((n, kw, 2)), "nwp": np.array([len(e.waypoints) for e in eps], dtype=np.int64),
        "rem": np.zeros((n, kw)),
        "discs": np.zeros((n, kd, 3)), "nd": np.array([len(e.discs) for e in eps], dtype=np.int64),
        "movers": np.zeros((n, km, 6)), "nm": np.array([len(e.movers) for e in eps], dtype=np.int64),
    }
    for i, e in enumerate(eps):
        w = np.asarray(e.waypoints, dtype=np.float64)
        a["wp"][i, :len(w)] = w
        seg = np.hypot(*np.diff(w, axis=0).T) if len(w) > 1 else np.zeros(0)
        a["rem"][i, :len(w)] = np.concatenate([np.cumsum(seg[::-1])[::-1], [0.0]])
        if e.discs:
            a["discs"][i, :len(e.discs)] = e.discs
        if e.movers:
            a["movers"][i, :len(e.movers)] = mover_array(e.movers)
    return a
