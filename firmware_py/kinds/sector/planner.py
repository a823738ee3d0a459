"""The sector kind's local planner (`LocalPlanner`): sub-goals round remembered
obstacles on the robot's map, searched off the tick (`recoveries.PlannedTarget`
posts the questions).

`LocalPlanner.target(x, y, waypoint, memory)` is the point the policy steers
to. While no remembered point comes within `obstacle_clear_mm` of the straight
line to the waypoint it is the waypoint itself, so on the known map the policy
drives exactly as trained. Once one does (for this waypoint: `reset()` per
mission item), the planner runs Dijkstra on a `raster_mm` raster of a window
round the robot and the waypoint: map walls grown by `wall_clear_mm` and
remembered points grown by `obstacle_clear_mm` are closed, and cells within
`soft_mm` of a point cost up to `weight` times more (nav2's inflation cost: the
path keeps its distance where there is room and squeezes through where there is
not). The target is then the furthest cell, within `lookahead_mm` along the
path, that the robot sees in a straight line keeping `los_clear_mm` from every
point, or the waypoint itself when that line is clear. The learnt policy was
trained to reach a point it can see with walls beside its line; the planner
hands it such points. `whole_map` searches cover the whole map (a recovery's
global re-plan), and `refuge` finds where to stand aside for a body that will
not give way.

The work is bounded: the raster window is at most (`max_plan_mm` + 2 x
`window_mm`) square and at most `config.MAX_WINDOW_CELLS` raster cells a side
(farther waypoints are driven at without planning until they are near
enough), and Dijkstra runs again only when the remembered set or the waypoint
changes. Pure stdlib (the robot has no numpy); the twin's bench runs this same
code.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable

from firmware_py import robot_spec
from firmware_py.kinds.sector.config import LocalPlannerConfig
from firmware_py.kinds.sector.memory import ObstacleMemory
from firmware_py.mapdata import OccupancyGrid, wall_gap, wall_within

_SQRT2 = 1.4142
_UNKNOWN = 2  # a raster cell of the map's configuration space not computed yet


def refuge_mm(radius_mm: int) -> int:
    """How far off a person's line a body of `radius_mm` gives way (LocalPlanner.refuge): two radii
    and a margin (a person walking a 500 mm corridor is up to 100 mm off its middle)."""
    return 2 * radius_mm + 150


REFUGE_MM = refuge_mm(robot_spec.ROBOT_RADIUS_MM)  # the built-in robot's
REFUGE_SEARCH_MM = 5000  # giving way: at a place at most this far along the way (a maze junction metres back)


Cell = tuple[int, int]


def _segment_distance(px: float, py: float, x: float, y: float, dx: float, dy: float, l2: float) -> float:
    """Distance from (px, py) to the segment from (x, y) along (dx, dy) (l2 its squared length)."""
    t = 0.0 if l2 == 0 else max(0.0, min(1.0, ((px - x) * dx + (py - y) * dy) / l2))
    return math.hypot(x + t * dx - px, y + t * dy - py)


def _segment_keeps(x: float, y: float, tx: float, ty: float, memory: ObstacleMemory, clear: float) -> bool:
    """No remembered point within `clear` mm of the segment (x, y) -> (tx, ty)."""
    dx, dy = tx - x, ty - y
    l2 = dx * dx + dy * dy
    return all(_segment_distance(px, py, x, y, dx, dy, l2) >= clear for px, py, _ in memory.points.values())


class LocalPlanner:
    """Sub-goals round remembered obstacles on the policy's map (see the module docstring)."""

    def __init__(self, grid: OccupancyGrid, cfg: LocalPlannerConfig,
                 radius_mm: int = robot_spec.ROBOT_RADIUS_MM) -> None:
        self.grid = grid
        self.cfg = cfg
        self.radius_mm = radius_mm  # the body's (firmware_py.layout)
        r = cfg.raster_mm
        self.nx = grid.width * grid.cell_mm // r
        self.ny = grid.height * grid.cell_mm // r
        # the map's own configuration space (raster centres clear of walls by wall_clear_mm), filled in
        # cell by cell as windows need it (_UNKNOWN until then): a tick never pays for the whole map
        self._map_free = bytearray([_UNKNOWN]) * (self.nx * self.ny)
        self._wall_cost: list[float] = [-1.0] * (self.nx * self.ny)  # inflation cost of the map's walls
        self.plans = 0  # Dijkstra runs (telemetry / benchmarks)
        self._active: tuple[int, int] | None = None
        self._grown_version = -1
        self._closed: set[Cell] = set()
        self._cost: dict[Cell, float] = {}
        self._plan_key: tuple[int, int, int] | None = None
        self._window = (0, 0, -1, -1)
        self._dist: dict[Cell, float] = {}
        self._global = False  # the last search covered the whole map
        self.detouring = False  # the last target was not the waypoint
        self.blocked = False  # the window's search found no way from the robot to the waypoint
        self.no_route = False  # the whole map's search found none either
        self.route_mm = 0.0  # the length of the way from the robot to the waypoint as last planned
        # the whole map's route is closed ahead and the robot holds for it to open (`_plan`): since when
        self.held = False
        self._closed_since_us: int | None = None

    def sharing_map(self) -> LocalPlanner:
        """A second planner on this map sharing its configuration-space caches (filled lazily by both;
        the worker's own, used on its thread only): a second question must not disturb the first's
        held route and grown points."""
        other = LocalPlanner(self.grid, self.cfg, self.radius_mm)
        other._map_free, other._wall_cost = self._map_free, self._wall_cost
        return other

    def reset(self, points: bool = False) -> None:
        """A new waypoint (mission item): drive straight until something is in the way. `points`: the
        next question's points are another set at the same version (`PlannedTarget._closed_before`),
        grow them anew."""
        if points:
            self._grown_version = -1
        self._active = None
        self._plan_key = None
        self._global = False
        self.detouring = self.blocked = self.no_route = self.held = False
        self._closed_since_us = None

    # --- the grown obstacles ----------------------------------------------------------------
    def _grow(self, memory: ObstacleMemory) -> None:
        if memory.version == self._grown_version:
            return
        self._grown_version = memory.version
        cfg = self.cfg
        r = cfg.raster_mm
        closed: set[Cell] = set()
        cost: dict[Cell, float] = {}
        c2, s2 = cfg.obstacle_clear_mm ** 2, cfg.soft_mm ** 2
        span = cfg.soft_mm - cfg.obstacle_clear_mm
        k = cfg.soft_mm // r + 1
        for px, py, _ in memory.points.values():
            ix, iy = px // r, py // r
            for dx in range(-k, k + 1):
                cx = (ix + dx) * r + r // 2 - px
                for dy in range(-k, k + 1):
                    cy = (iy + dy) * r + r // 2 - py
                    d2 = cx * cx + cy * cy
                    if d2 >= s2:
                        continue
                    cell = (ix + dx, iy + dy)
                    if d2 < c2:
                        closed.add(cell)
                    else:
                        c = cfg.weight * (cfg.soft_mm - math.sqrt(d2)) / span
                        if c > cost.get(cell, 0.0):
                            cost[cell] = c
        self._closed, self._cost = closed, cost

    def _wall_weight(self, ix: int, iy: int) -> float:
        """The inflation cost of the map's walls at a raster cell (nav2's inflation layer over the
        static map, with the points' soft_mm and weight): a route keeps to the middle of corridors
        and doors and turns wide round a door's jamb, where the table drives as trained."""
        i = iy * self.nx + ix
        v = self._wall_cost[i]
        if v < 0:
            cfg = self.cfg
            r = cfg.raster_mm
            d = wall_gap(self.grid, ix * r + r // 2, iy * r + r // 2, cfg.soft_mm)
            span = max(1, cfg.soft_mm - cfg.wall_clear_mm)
            v = 0.0 if d >= cfg.soft_mm else cfg.weight * min(1.0, (cfg.soft_mm - d) / span)
            self._wall_cost[i] = v
        return v

    def _open_map(self, c: Cell) -> bool:
        """The raster cell is inside the map and its centre clear of walls by wall_clear_mm."""
        ix, iy = c
        if not (0 <= ix < self.nx and 0 <= iy < self.ny):
            return False
        i = iy * self.nx + ix
        v = self._map_free[i]
        if v == _UNKNOWN:
            r = self.cfg.raster_mm
            v = 0 if wall_within(self.grid, ix * r + r // 2, iy * r + r // 2, self.cfg.wall_clear_mm) else 1
            self._map_free[i] = v
        return v == 1

    def _open(self, c: Cell) -> bool:
        return c not in self._closed and self._open_map(c)

    def _in_way(self, x: float, y: float, wx: float, wy: float, memory: ObstacleMemory) -> bool:
        """A remembered point within obstacle_clear_mm of the segment robot -> waypoint."""
        return not _segment_keeps(x, y, wx, wy, memory, self.cfg.obstacle_clear_mm)

    def _line_clear(self, x: float, y: float, tx: float, ty: float, memory: ObstacleMemory) -> bool:
        """The straight line stays in the map's free space (its first 150 mm and last 100 mm excepted:
        the robot may stand closer to a wall than the raster's margin, the target is a point) and goes
        no nearer than los_clear_mm to any remembered point, unless the robot is already nearer it
        and the line does not get nearer still (moving away from an obstacle is always clear)."""
        if not self.map_sight(x, y, tx, ty):
            return False
        los = self.cfg.los_clear_mm
        dx, dy = tx - x, ty - y
        l2 = dx * dx + dy * dy
        for px, py, _ in memory.points.values():
            d = _segment_distance(px, py, x, y, dx, dy, l2)
            if d < los and d < math.hypot(px - x, py - y) - 1.0:
                return False
        return True

    def map_sight(self, x: float, y: float, tx: float, ty: float) -> bool:
        """`_line_clear`'s part on the map alone: its walls (and margins) leave the straight line free."""
        r = self.cfg.raster_mm
        length = math.hypot(tx - x, ty - y)
        n = int(2 * length / r) + 1
        for i in range(1, n + 1):
            f = i / n
            along = f * length
            if along < 150 or length - along < 100:
                continue
            if not self._open_map((int((x + f * (tx - x)) // r), int((y + f * (ty - y)) // r))):
                return False
        return self._body_clear(x, y, tx, ty)

    def _body_clear(self, x: float, y: float, tx: float, ty: float) -> bool:
        """The robot's disc (radius + 10 mm) driven straight toward (tx, ty) touches no map wall in
        the part of the line `_line_clear`'s raster test leaves out, its first 150 mm (checked every
        25 mm from 25 mm on: a door's jamb the line passes at 100 mm is a collision the raster's
        margin does not see there)."""
        length = math.hypot(tx - x, ty - y)
        if length < 1.0:
            return True
        ux, uy = (tx - x) / length, (ty - y) / length
        m = self.radius_mm + 10
        along = 25.0
        while along <= min(length, 175.0):
            if wall_within(self.grid, round(x + along * ux), round(y + along * uy), m):
                return False
            along += 25.0
        return True

    # --- the plan --------------------------------------------------------------------------------
    def _plan(self, x: float, y: float, wx: int, wy: int, version: int, whole_map: bool = False,
              asked_us: int = 0) -> None:
        """Dijkstra from the waypoint over a window round the robot and the waypoint (`whole_map`:
        over the whole map, a global re-plan), unless the last search still holds. A whole-map route
        the robot is on, closed ahead by points seen since, is held to for `wait_us` (`held`: the robot
        stands) before the search runs again, so a mover walking across it does not send the robot
        to and fro between two doors."""
        cfg = self.cfg
        r = cfg.raster_mm
        key = (wx, wy, version)
        ix, iy = int(x // r), int(y // r)
        x0, y0, x1, y1 = self._window
        if key == self._plan_key and whole_map == self._global and x0 <= ix <= x1 and y0 <= iy <= y1 and (
                not whole_map or self._path_open(ix, iy, 0)):
            return
        if whole_map and self._global and self._plan_key is not None and self._plan_key[:2] == key[:2]:
            if self._path_open(ix, iy):
                self._plan_key = key  # the whole map is searched again only when the way ahead closed
                self._closed_since_us = None
                return
            on_route = any((ix + dx, iy + dy) in self._dist for dx in (-1, 0, 1) for dy in (-1, 0, 1))
            if on_route:
                if self._closed_since_us is None:
                    self._closed_since_us = asked_us
                if asked_us - self._closed_since_us < cfg.wait_us:
                    self.held = True
                    return
        self._closed_since_us = None
        self._plan_key = key
        self._global = whole_map
        self.plans += 1
        w = cfg.window_mm
        if whole_map:
            x0, y0, x1, y1 = 0, 0, self.nx - 1, self.ny - 1
        else:
            x0 = max(0, int((min(x, wx) - w) // r))
            x1 = min(self.nx - 1, int((max(x, wx) + w) // r))
            y0 = max(0, int((min(y, wy) - w) // r))
            y1 = min(self.ny - 1, int((max(y, wy) + w) // r))
        self._window = (x0, y0, x1, y1)
        goal = (min(max(wx // r, x0), x1), min(max(wy // r, y0), y1))  # a waypoint on the map's far edge
        # the waypoint's own cells stay open: the ground station's waypoints keep robot radius + 50 mm
        # from any obstacle it placed, closer than the grown points may reach
        near_goal = {(goal[0] + dx, goal[1] + dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)
                     if math.hypot((goal[0] + dx) * r + r // 2 - wx, (goal[1] + dy) * r + r // 2 - wy) <= r * 1.1}
        # the window as flat arrays with a closed border of one cell (no bounds checks in the loop):
        # open[i] (map free and not grown over, or the waypoint's own cells) and the step weight
        wd, ht = x1 - x0 + 3, y1 - y0 + 3
        closed, cost = self._closed, self._cost
        open_ = bytearray(wd * ht)
        weight = [1.0] * (wd * ht)
        for cy in range(y0, y1 + 1):
            row = (cy - y0 + 1) * wd + 1 - x0
            for cx in range(x0, x1 + 1):
                if (cx, cy) not in closed and self._open_map((cx, cy)):
                    open_[row + cx] = 1
                    weight[row + cx] = 1.0 + self._wall_weight(cx, cy)
        for cx, cy in near_goal:
            if x0 <= cx <= x1 and y0 <= cy <= y1:
                open_[(cy - y0 + 1) * wd + cx - x0 + 1] = 1
        for (cx, cy), c in cost.items():
            if x0 <= cx <= x1 and y0 <= cy <= y1:
                i = (cy - y0 + 1) * wd + cx - x0 + 1
                weight[i] = max(weight[i], 1.0 + c)
        inf = math.inf
        dist_a = [inf] * (wd * ht)
        g = (goal[1] - y0 + 1) * wd + goal[0] - x0 + 1
        dist_a[g] = 0.0
        heap: list[tuple[float, int]] = [(0.0, g)]
        # (index offset, step length, the two orthogonal offsets a diagonal step must not cut between)
        steps = [(1, 1.0, 0, 0), (-1, 1.0, 0, 0), (wd, 1.0, 0, 0), (-wd, 1.0, 0, 0),
                 (wd + 1, _SQRT2, 1, wd), (wd - 1, _SQRT2, -1, wd), (1 - wd, _SQRT2, 1, -wd),
                 (-1 - wd, _SQRT2, -1, -wd)]
        pop, push = heapq.heappop, heapq.heappush
        while heap:
            d, i = pop(heap)
            if d > dist_a[i]:
                continue
            for off, step, ox, oy in steps:
                n = i + off
                if not open_[n] or (ox and not (open_[i + ox] and open_[i + oy])):
                    continue  # closed, or a diagonal cutting a corner
                nd = d + step * weight[n]
                if nd < dist_a[n]:
                    dist_a[n] = nd
                    push(heap, (nd, n))
        self._dist = {(i % wd - 1 + x0, i // wd - 1 + y0): d for i, d in enumerate(dist_a) if d < inf}

    def _downhill(self, c: Cell) -> tuple[float, Cell]:
        """The last search's neighbour of raster cell `c` nearest the waypoint, and its distance."""
        dist = self._dist
        return min((dist.get((c[0] + dx, c[1] + dy), math.inf), (c[0] + dx, c[1] + dy))
                   for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy)

    def _route_length(self, cur: Cell, max_steps: int = 4000) -> float:
        """Length (mm) of the last search's way from raster cell `cur` down to the waypoint (the
        distances are costs, inflation included: the way is walked to measure it)."""
        dist, r = self._dist, self.cfg.raster_mm
        c, total = cur, 0.0
        for _ in range(max_steps):
            d, nxt = self._downhill(c)
            if d >= dist[c]:
                break
            total += r * (_SQRT2 if nxt[0] != c[0] and nxt[1] != c[1] else 1.0)
            c = nxt
        return total

    def _path_open(self, ix: int, iy: int, cells: int = 30) -> bool:
        """The last search's way from raster cell (ix, iy) (or a cell next to it: the robot may stand
        nearer a wall or a point than the raster's margins) stays open for `cells` steps (or to the
        waypoint): remembered points seen since have not closed it."""
        dist = self._dist
        near = [c for c in ((ix + dx, iy + dy) for dx in (0, -1, 1, -2, 2) for dy in (0, -1, 1, -2, 2))
                if c in dist]
        if not near:
            return False
        c = near[0]
        for _ in range(cells):
            d, nxt = self._downhill(c)
            if d >= dist[c]:
                return True
            if nxt in self._closed:
                return False
            c = nxt
        return True

    def target(self, x: float, y: float, waypoint: tuple[int, int], memory: ObstacleMemory,
               whole_map: bool = False, asked_us: int = 0) -> tuple[float, float]:
        """The point the policy steers to this tick (world mm). `whole_map`: plan over the whole
        map (a global re-plan: `no_route` says when the waypoint cannot be reached at all).
        `held`: the whole map's route is closed ahead and held to a while (`_plan`): stand."""
        wx, wy = waypoint
        self.blocked = self.no_route = self.held = False
        last_route_mm = self.route_mm
        self.route_mm = math.hypot(wx - x, wy - y)
        if not whole_map and self.route_mm > self.cfg.max_plan_mm:
            self.detouring = False  # far: the ground station's waypoints are <= 1 m apart, a far goal
            return float(wx), float(wy)  # is driven at until it is near enough to plan round things
        if self._active != waypoint:
            if not whole_map and (not memory.points or not self._in_way(x, y, wx, wy, memory)):
                self.detouring = False
                return float(wx), float(wy)
            self._active = waypoint  # something was in the way: plan until this waypoint is reached
        self._grow(memory)
        if self._line_clear(x, y, wx, wy, memory):
            self.detouring = False
            return float(wx), float(wy)
        self._plan(x, y, wx, wy, memory.version, whole_map, asked_us)
        if self.held:
            self.route_mm = last_route_mm  # the route is still the way (benchmarks measure progress on it)
            return x, y
        dist = self._dist
        r = self.cfg.raster_mm
        ix, iy = int(x // r), int(y // r)
        cur = (ix, iy)
        if cur not in dist:
            # inside a grown obstacle or a wall's margin: start from the best cell nearby in reach
            near = [(dist[c] + math.hypot(c[0] - ix, c[1] - iy), c)
                    for c in self._cells_in_reach(x, y, memory, lambda c: c in dist)]
            if not near:
                # no way from here: the tick's side starts the recoveries (Recovery), meanwhile
                # toward the waypoint behind the motion guard (a mover may step aside)
                self.detouring = False
                self.blocked = True
                self.no_route = whole_map
                return float(wx), float(wy)
            if whole_map:  # the nearest such cell: one further on may lie round a corner of the map
                cur = min((math.hypot(c[0] - ix, c[1] - iy), d, c) for d, c in near)[2]
            else:
                cur = min(near)[1]
        self.route_mm = self._route_length(cur)
        path = [cur]
        for _ in range(self.cfg.lookahead_mm // r + 1):
            c = path[-1]
            d, nxt = self._downhill(c)
            if d >= dist[c]:
                break
            path.append(nxt)
        # the whole map's route passes doors and corners of the map: every target there is one the
        # robot sees in a straight line (a window's detour goes round points in the open)
        best = path[0]
        for c in path[1 if whole_map else 2:]:  # the furthest the robot sees (not the last before one it
            if self._line_clear(x, y, c[0] * r + r / 2, c[1] * r + r / 2, memory):  # does not: a path
                best = c  # bending round a point hides its next cells and shows the ones after them)
        if best == path[0] and len(path) > 1 and self._body_clear(x, y, path[1][0] * r + r / 2,
                                                                  path[1][1] * r + r / 2):
            # none further in sight: the next cell unless the body would clip a wall toward it (a window's
            # detour; a route squeezing between a point and a wall nearer than los_clear_mm, open at
            # obstacle_clear_mm, has none of its cells in plain sight, and steering to the robot's own
            # cell held it there for good)
            best = path[1]
        self.detouring = True
        return best[0] * r + r / 2, best[1] * r + r / 2

    def _cells_in_reach(self, x: float, y: float, memory: ObstacleMemory,
                        ok: Callable[[Cell], bool]) -> list[Cell]:
        """Raster cells within 3 of the robot's for which `ok(cell)` holds and that it reaches in a
        straight line without going nearer a remembered point (not one across the obstacle) and
        without its body clipping a map wall on the way (not one round a door's jamb): where a search
        starts when the robot stands inside a grown obstacle or a wall's margin."""
        r = self.cfg.raster_mm
        ix, iy = int(x // r), int(y // r)
        return [c for c in ((ix + dx, iy + dy) for dx in range(-3, 4) for dy in range(-3, 4))
                if ok(c) and _segment_keeps(x, y, c[0] * r + r / 2, c[1] * r + r / 2, memory,
                                            self.radius_mm + 10)
                and self._body_clear(x, y, c[0] * r + r / 2, c[1] * r + r / 2)]

    def refuge(self, x: float, y: float, memory: ObstacleMemory) -> tuple[int, int] | None:
        """Where to stand aside for the body nearest the robot (a person who does not give way), or
        None: the raster cell nearest by way (Dijkstra over the map's free space, the remembered points
        grown, up to `REFUGE_SEARCH_MM`) whose centre lies `refuge_mm` or more off the line the body
        walks and as far or more from the body: a side corridor or a room's corner. That line runs
        through the robot along the grid axis nearest the body-to-robot direction (a corridor runs
        along an axis, and a person walking in one is rarely in its middle)."""
        nearest = memory.nearest(x, y)
        if nearest is None:
            return None
        px, py = nearest
        ux, uy = x - px, y - py
        n = math.hypot(ux, uy)
        if n < 1.0:
            return None
        ux, uy = (math.copysign(1.0, ux), 0.0) if abs(ux) >= abs(uy) else (0.0, math.copysign(1.0, uy))
        self._grow(memory)
        r = self.cfg.raster_mm
        starts = self._cells_in_reach(x, y, memory, self._open)
        dist: dict[Cell, float] = {}
        heap: list[tuple[float, Cell]] = []
        for c in starts:
            d = math.hypot(c[0] * r + r / 2 - x, c[1] * r + r / 2 - y) / r
            if d < dist.get(c, math.inf):
                dist[c] = d
                heapq.heappush(heap, (d, c))
        limit = REFUGE_SEARCH_MM / r
        refuge = refuge_mm(self.radius_mm)
        while heap:
            d, c = heapq.heappop(heap)
            if d > dist[c] or d > limit:
                continue
            cx, cy = c[0] * r + r / 2, c[1] * r + r / 2
            if (abs((cx - x) * uy - (cy - y) * ux) >= refuge
                    and (cx - px) ** 2 + (cy - py) ** 2 >= refuge ** 2):
                return round(cx), round(cy)
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    nb = (c[0] + dx, c[1] + dy)
                    if (dx or dy) and self._open(nb) and (
                            not (dx and dy) or (self._open((c[0] + dx, c[1])) and self._open((c[0], c[1] + dy)))):
                        nd = d + (_SQRT2 if dx and dy else 1.0)
                        if nd < dist.get(nb, math.inf):
                            dist[nb] = nd
                            heapq.heappush(heap, (nd, nb))
        return None
