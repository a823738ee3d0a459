"""Navigation scenarios: a map, an episode, and obstacles the planner does not know.

The one definition of a scenario episode, used by the twin's rollouts
(`ground_station.learn.sector.obstacles`), the pymunk plant
(`sim_bridge.obstacles.ObstacleLayer`), `qnav bench nav` and `qnav demo
--obstacles/--movers`. An `Episode` is plain data (JSON round trip):
start pose, goal, the planner's waypoints on the known map, static discs and
movers; `make_episode(gridmap, start, goal, heading, k, m, rng)` builds one
from a seeded `numpy.random.Generator`.

**Static obstacles** are discs of radius 100-200 mm placed on or beside the
planned path: the centre at a uniform point of the waypoint polyline between
15 % and 85 % of its length, moved sideways by up to `LATERAL_MM`. One is
kept only if the set stays **detourable**:

1. every disc lies in free space (overlaps no obstacle cell or the border);
2. the start pose and every waypoint keep >= robot radius + `WAYPOINT_CLEAR_MM`
   from every disc surface (the robot can still stand on each waypoint, as
   the controller needs to pass within `GOAL_TOLERANCE_MM` of it);
3. on a `RASTER_MM` raster of the configuration space (points where the
   robot's disc grown by `CSPACE_MARGIN_MM` touches no obstacle cell,
   border or disc), consecutive waypoints (from the start) stay connected
   (8-connected), and the shortest raster path between them is at most
   `DETOUR_MAX_MM` longer than the same path without the discs: a local
   detour exists. Corridors one cell (500 mm) wide never pass this with a
   disc in them (500 - 200 < 300 + 2 x 25 mm), so obstacles land in rooms and
   open stretches; where no position passes after `TRIES` draws, fewer than
   k discs are placed (`Episode.discs` says how many).

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

**Movers** are discs of `MOVER_RADIUS_MM` walking straight lines at a
pedestrian's slow pace (`MOVER_SPEED_MM_S`, uniform in that range, random
direction), starting in free space at least `MOVER_START_MM` from the robot,
bouncing off walls, discs and the robot (`sim_bridge.obstacles.step_movers`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numba
import numpy as np

from firmware_py import robot_spec
from ground_station.learn.sector.twin import disc_hits
from ground_station.maps import GridMap, MapError, bfs_distances, octile_distances
from ground_station.maps.planner import plan_waypoints
from sim_bridge.obstacles import mover_array

LATERAL_MM = 300.0
DISC_RADIUS_MM = (100.0, 200.0)
WAYPOINT_CLEAR_MM = 50.0
RASTER_MM = 50.0
CSPACE_MARGIN_MM = 75.0
DETOUR_MAX_MM = 1500.0
TRIES = 40
MOVER_RADIUS_MM = 150.0
MOVER_SPEED_MM_S = (300.0, 600.0)
MOVER_START_MM = 1200.0
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


# --- configuration space ---------------------------------------------------------

@numba.njit(cache=True)
def _cspace(occ, cell, discs, step, clear):
    """bool raster (ny, nx) of points (ix+0.5, iy+0.5)*step where a disc of
    radius `clear` touches no obstacle cell, border (the twin's `disc_hits`) or
    disc. Row 0 = south."""
    h, w = occ.shape
    nx = int(w * cell / step)
    ny = int(h * cell / step)
    out = np.zeros((ny, nx), dtype=np.bool_)
    for iy in range(ny):
        y = (iy + 0.5) * step
        for ix in range(nx):
            x = (ix + 0.5) * step
            ok = not disc_hits(occ, h, w, cell, x, y, clear)
            if ok:
                for k in range(discs.shape[0]):
                    d = clear + discs[k, 2]
                    if (x - discs[k, 0]) ** 2 + (y - discs[k, 1]) ** 2 < d * d:
                        ok = False
                        break
            out[iy, ix] = ok
    return out


def _raster_index(free: np.ndarray, x: float, y: float) -> tuple[int, int]:
    """Nearest free raster point to (x, y) mm (the point itself when free)."""
    ny, nx = free.shape
    ix = min(nx - 1, max(0, int(x // RASTER_MM)))
    iy = min(ny - 1, max(0, int(y // RASTER_MM)))
    if free[iy, ix]:
        return ix, iy
    best, pick = math.inf, (ix, iy)
    for yy in range(max(0, iy - 3), min(ny, iy + 4)):
        for xx in range(max(0, ix - 3), min(nx, ix + 4)):
            if free[yy, xx]:
                d = (xx - ix) ** 2 + (yy - iy) ** 2
                if d < best:
                    best, pick = d, (xx, yy)
    return pick


def _leg_lengths(gridmap: GridMap, points: list[tuple[float, float]], discs: np.ndarray,
                 margin: float = CSPACE_MARGIN_MM) -> list[float]:
    occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
    cell = gridmap.cell_size_m * 1000.0
    free = _cspace(occ, cell, discs.reshape(-1, 3), RASTER_MM, robot_spec.ROBOT_RADIUS_MM + margin)
    return _raster_legs(free, points)


def _raster_legs(free: np.ndarray, points: list[tuple[float, float]]) -> list[float]:
    """Shortest 8-connected raster path (mm) of each leg points[i] -> points[i+1] on `free`."""
    out = []
    for a, b in zip(points[:-1], points[1:], strict=True):
        ia, ib = _raster_index(free, *a), _raster_index(free, *b)
        # 8-connected raster path (no corner cutting), the shared shortest-path module
        out.append(float(octile_distances(~free, ib[0], ib[1])[ia[1], ia[0]]) * RASTER_MM)
    return out


def detourable(gridmap: GridMap, start: tuple[float, float], waypoints: list[tuple[float, float]],
               discs: list[tuple[float, float, float]], base: list[float] | None = None) -> bool:
    """The definition in the module docstring: discs in free space, start and
    waypoints clear of them, and every leg connected with a detour of at most
    DETOUR_MAX_MM over the leg without discs (`base`, computed if not given)."""
    occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
    cell = gridmap.cell_size_m * 1000.0
    arr = np.asarray(discs, dtype=np.float64).reshape(-1, 3)
    for x, y, r in arr:  # 1. in free space (a point-sized robot: the disc itself)
        if _disc_blocked(occ, cell, x, y, r):
            return False
    keep = robot_spec.ROBOT_RADIUS_MM + WAYPOINT_CLEAR_MM
    for px, py in [start, *waypoints]:  # 2. start and waypoints clear
        for x, y, r in arr:
            if math.hypot(px - x, py - y) < r + keep:
                return False
    points = [start, *waypoints]
    if base is None:
        base = _leg_lengths(gridmap, points, np.zeros((0, 3)))
    legs = _leg_lengths(gridmap, points, arr)  # 3. connected, local detour
    return all(math.isfinite(a) and a <= b + DETOUR_MAX_MM for a, b in zip(legs, base, strict=True))


def _disc_blocked(occ: np.ndarray, cell: float, x: float, y: float, r: float) -> bool:
    h, w = occ.shape
    if x < r or y < r or x > w * cell - r or y > h * cell - r:
        return True
    top = h * cell
    for row in range(max(0, int((top - y - r) // cell)), min(h, int((top - y + r) // cell) + 1)):
        ylo = top - (row + 1) * cell
        for col in range(max(0, int((x - r) // cell)), min(w, int((x + r) // cell) + 1)):
            if occ[row, col]:
                px = min(max(x, col * cell), (col + 1) * cell)
                py = min(max(y, ylo), ylo + cell)
                if (x - px) ** 2 + (y - py) ** 2 < r * r:
                    return True
    return False


def _point_along(points: list[tuple[float, float]], s: float) -> tuple[float, float, float]:
    """Point at arc length s along the polyline and the segment's direction (rad)."""
    for (ax, ay), (bx, by) in zip(points[:-1], points[1:], strict=True):
        seg = math.hypot(bx - ax, by - ay)
        if s <= seg or (bx, by) == points[-1]:
            t = min(1.0, s / seg) if seg > 0 else 0.0
            return ax + t * (bx - ax), ay + t * (by - ay), math.atan2(by - ay, bx - ax)
        s -= seg
    x, y = points[-1]
    return x, y, 0.0


def place_discs(gridmap: GridMap, start: tuple[float, float], waypoints: list[tuple[float, float]],
                k: int, rng: np.random.Generator) -> list[tuple[float, float, float]]:
    """Up to k detourable discs on or beside the path start -> waypoints."""
    points = [start, *waypoints]
    total = sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(points[:-1], points[1:], strict=True))
    discs: list[tuple[float, float, float]] = []
    if k <= 0 or total <= 0:
        return discs
    base = _leg_lengths(gridmap, points, np.zeros((0, 3)))
    for _ in range(k):
        for _try in range(TRIES):
            x, y, ang = _point_along(points, float(rng.uniform(0.15, 0.85)) * total)
            off = float(rng.uniform(-LATERAL_MM, LATERAL_MM))
            x, y = x - off * math.sin(ang), y + off * math.cos(ang)
            r = float(rng.uniform(*DISC_RADIUS_MM))
            cand = (round(x, 1), round(y, 1), round(r, 1))
            if detourable(gridmap, start, waypoints, [*discs, cand], base):
                discs.append(cand)
                break
    return discs


def place_movers(gridmap: GridMap, start: tuple[float, float], discs: list[tuple[float, float, float]],
                 m: int, rng: np.random.Generator, speed: tuple[float, float] = MOVER_SPEED_MM_S,
                 yields: bool = True) -> list[tuple[float, ...]]:
    """m movers in free space away from the start (fewer if no place is found), at a speed uniform in
    `speed` (mm/s); `yields`: whether they step aside for the robot (sim_bridge.obstacles)."""
    occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
    cell = gridmap.cell_size_m * 1000.0
    cells = gridmap.free_cells()
    h = gridmap.height
    out: list[tuple[float, ...]] = []
    r = MOVER_RADIUS_MM
    for _ in range(m):
        for _try in range(TRIES):
            col, row = cells[int(rng.integers(len(cells)))]
            x = (col + 0.5) * cell + float(rng.uniform(-0.3, 0.3)) * cell
            y = (h - row - 0.5) * cell + float(rng.uniform(-0.3, 0.3)) * cell
            if math.hypot(x - start[0], y - start[1]) < MOVER_START_MM or _disc_blocked(occ, cell, x, y, r):
                continue
            if any(math.hypot(x - dx, y - dy) < r + dr for dx, dy, dr in discs):
                continue
            v = float(rng.uniform(*speed))
            a = float(rng.uniform(-math.pi, math.pi))
            out.append((round(x, 1), round(y, 1), round(v * math.cos(a), 1), round(v * math.sin(a), 1), r,
                        1.0 if yields else 0.0))
            break
    return out


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
        free = _cspace(occ, gridmap.cell_size_m * 1000.0, np.zeros((0, 3)), RASTER_MM,
                       robot_spec.ROBOT_RADIUS_MM + margin)
        _FREE_CACHE[key] = free
    return free


def _close_disc(free: np.ndarray, disc: tuple[float, float, float], clear: float) -> np.ndarray:
    """`free` with the raster points a disc closes for a robot disc of radius `clear` removed:
    the same test as `_cspace`'s disc loop, so the result equals `_cspace` with the disc."""
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
    """Every leg points[i] -> points[i+1] connected on `free` (as `_raster_legs` finite): all points
    in the first one's component. 4-connected reachability equals 8-connected without corner cutting."""
    idx = [_raster_index(free, *p) for p in points]
    dist = bfs_distances(~free, idx[0][0], idx[0][1])
    return all(dist[iy, ix] >= 0 for ix, iy in idx)


class _Route:
    """One planned route (start, then the waypoints) on the map's configuration-space raster
    (robot radius + CSPACE_MARGIN_MM): what every candidate blocking disc of the route shares."""

    def __init__(self, gridmap: GridMap, points: list[tuple[float, float]]) -> None:
        self.gridmap = gridmap
        self.points = points
        self.free = _free_raster(gridmap, CSPACE_MARGIN_MM)
        self.idx = [_raster_index(self.free, *p) for p in points]
        self._fields: list[np.ndarray] | None = None

    def fields(self) -> list[np.ndarray]:
        """Octile distance fields (raster steps) from every point without discs, computed once."""
        if self._fields is None:
            self._fields = [octile_distances(~self.free, ix, iy) for ix, iy in self.idx]
        return self._fields

    def base(self) -> list[float]:
        """Leg lengths (mm) without discs: `_leg_lengths` of the route with no discs."""
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
            # the legs' lengths with the disc (as `detourable`), recomputed only where a shortest
            # path without the disc ran through a raster point the disc closes
            f = self.fields()
            base = self.base()
            closed = self.free & ~free
            idx = [_raster_index(free, *p) for p in self.points]
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
        x, y, ang = _point_along(points, float(rng.uniform(*BLOCK_SPAN)) * total)
        off = float(rng.uniform(-BLOCK_LATERAL_MM, BLOCK_LATERAL_MM))
        x, y = x - off * math.sin(ang), y + off * math.cos(ang)
        r = float(rng.uniform(*BLOCK_RADIUS_MM))
        cand = (round(x, 1), round(y, 1), round(r, 1))
        if _disc_blocked(occ, cell, *cand):  # a. in free space
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
