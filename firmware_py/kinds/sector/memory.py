"""The sector kind's obstacle memory (`ObstacleMemory`): what the robot has seen
that its map does not show.

It keeps the end points of range readings the map does not explain
(`firmware_py.mapdata.unmapped_ends`), in world millimetres, one per 50 mm
square, each stamped with the controller clock (sim time in HIL) and forgotten
`memory_us` after it was last seen: a person who walked on leaves no wall
behind, a box in view is seen again every tick. A reading clears the points
inside its cone that lie nearer than it by `clear_margin_mm` (nav2's obstacle
layer clears by raytracing: a cone reports its nearest echo), so a mover that
stepped aside is gone at once; points the robot is going round, and points
pinned by a global re-plan, are kept `route_memory_us` (a door found closed
stays closed while the robot goes round through another) unless a reading sees
through them. At most `max_points` points (the oldest go first).

A point in the blind gap between two cones where no body could stand unseen is
cleared (`_no_room`; why: docs/architecture.md, "Local re-planning on the robot").
"""

from __future__ import annotations

import bisect
import math

from firmware_py import robot_spec
from firmware_py.kinds.sector.config import LocalPlannerConfig
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.layout import Layout
from firmware_py.mapdata import OccupancyGrid, unmapped_ends


def _circular_order(angles: list[float]) -> tuple[list[float], list[int]]:
    """The sensor directions wrapped to [-pi, pi) and sorted, with their indices (`_nearest_sensor`)."""
    pairs = sorted(((a + math.pi) % (2 * math.pi) - math.pi, i) for i, a in enumerate(angles))
    return [a for a, _ in pairs], [i for _, i in pairs]


_KEY_MM = 50  # one remembered point per 50 mm square
# the sensor directions of robot_spec (the rays of `unmapped_ends`' fans share them)
_ANG = [a / 1000.0 for a in robot_spec.SENSOR_ANGLES_MRAD]
_ORDER = _circular_order(_ANG)  # the built-in robot's, once (a memory is built for every snapshot)
# ObstacleMemory.added counts new points this near the robot (at window_mm, 1 m, a person walking to
# and fro beside a disc that closes the only door made every round a "moving scene": no "no route")
MOVING_NEAR_MM = 700
# the smallest body the robot is built to see (the scenarios' discs are 100-200 mm, movers 150; the
# collision monitor's CONTACT_MM rests on the same size): a remembered point no disc of this radius
# through it could stand at unseen is cleared (ObstacleMemory._no_room)
MIN_BODY_RADIUS_MM = 100
_BODY_SLACK_MM = 30  # a ray must pass this far inside such a disc to rule it out (a box's corner, noise)
_BODY_STEPS = 24  # the discs through a point tried, by the direction of their centres
_BODY_DIRS = [(math.cos(2 * math.pi * k / _BODY_STEPS), math.sin(2 * math.pi * k / _BODY_STEPS))
              for k in range(_BODY_STEPS)]


def _nearest_sensor(rel: float, angles: list[float], order: tuple[list[float], list[int]]) -> int:
    """The direction nearest `rel` (radians), ties to the lowest: a scan's answer, from its 2 neighbours."""
    k = bisect.bisect_left(order[0], (rel + math.pi) % (2 * math.pi) - math.pi)
    a, b = order[1][k % len(angles)], order[1][k - 1]
    da, db = (abs((rel - angles[j] + math.pi) % (2 * math.pi) - math.pi) for j in (a, b))
    return a if (da, a) < (db, b) else b


Segment = tuple[float, float, float, float, float]  # start x, y, unit x, y, length


def _within(px: float, py: float, segs: list[Segment], max2: float, first: bool = False) -> list[Segment]:
    """The segments of `segs` nearer than sqrt(max2) to (px, py) (`first`: stop at the first one).
    One loop, no call per segment: a robot beside a body asks this some thousand times a tick (a
    distance function called per segment made `_no_room` the longest part of the tick's p99)."""
    out = []
    for g in segs:
        sx, sy, ux, uy, length = g
        dx, dy = px - sx, py - sy
        t = dx * ux + dy * uy
        t = 0.0 if t < 0.0 else (length if t > length else t)
        ex, ey = dx - t * ux, dy - t * uy
        if ex * ex + ey * ey < max2:
            out.append(g)
            if first:
                break
    return out


class ObstacleMemory:
    """Unmapped reading end points (world mm) with the time each was last seen, cleared by readings
    that see through them; points pinned by a global re-plan outlive `memory_us` (module docstring)."""

    def __init__(self, cfg: LocalPlannerConfig, layout: Layout = DEFAULT_LAYOUT) -> None:
        self.cfg = cfg
        # the sector readings' geometry (firmware_py.layout: the profile's, as the policy's sectors see it)
        self.layout = layout
        self._layout_arg = None if layout == DEFAULT_LAYOUT else layout  # unmapped_ends' (None: built-in)
        self._ang = _ANG if self._layout_arg is None else [a / 1000.0 for a in layout.angles_mrad]
        self._order = _ORDER if self._layout_arg is None else _circular_order(self._ang)
        self._mount = float(layout.mount_mm)
        self._half_fov = layout.fov_mrad / 2000.0
        # a moving scene's new points belong to a body that moved: remembered points this near one of them
        # are that body's (a person is about the robot's width; standing_by)
        self.body_mm = 2 * layout.robot_radius_mm
        self.points: dict[tuple[int, int], tuple[int, int, int]] = {}
        self.pinned: dict[tuple[int, int], int] = {}  # key -> kept until (controller clock)
        self.born: dict[tuple[int, int], int] = {}  # key -> when first seen (controller clock)
        self.version = 0  # bumped when a point is added or forgotten (not when one is seen again)
        # points added (a new 50 mm square) within MOVING_NEAR_MM of the robot since the memory began:
        # how much moves near it (a mover walking past in view across the room is not what closed the way)
        self.added = 0

    def observe(self, grid: OccupancyGrid, x_mm: int, y_mm: int, heading_mrad: int,
                ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...], now_us: int) -> None:
        """Remember this tick's unmapped end points (the fan's middle ray at the read distance), clear
        the points a reading sees through, and forget the ones not seen for `memory_us` (pinned ones
        when their pin runs out)."""
        cfg = self.cfg
        seen: set[tuple[int, int]] = set()
        near = MOVING_NEAR_MM * MOVING_NEAR_MM
        for _, _, ex, ey in unmapped_ends(grid, x_mm, y_mm, heading_mrad, ranges_mm, status, cfg.margin_mm,
                                          cfg.see_mm, self._layout_arg):
            key = (ex // _KEY_MM, ey // _KEY_MM)
            if key not in self.points:
                self.version += 1
                self.added += (ex - x_mm) ** 2 + (ey - y_mm) ** 2 <= near
                self.born[key] = now_us
            self.points[key] = (ex, ey, now_us)
            seen.add(key)
        old = self._seen_through(x_mm, y_mm, heading_mrad, ranges_mm, status, seen)
        old += self._no_room(x_mm, y_mm, heading_mrad, ranges_mm, status, seen.union(old))
        old += [p for p, v in self.points.items()
                if now_us - v[2] > cfg.memory_us and self.pinned.get(p, -1) < now_us and p not in old]
        if len(self.points) - len(old) > cfg.max_points:
            gone = set(old)
            by_age = sorted((p for p in self.points if p not in gone), key=lambda p: self.points[p][2])
            old += by_age[:len(self.points) - len(old) - cfg.max_points]
        for p in old:
            del self.points[p]
            self.pinned.pop(p, None)
            self.born.pop(p, None)
        self.version += bool(old)

    def _seen_through(self, x_mm: int, y_mm: int, heading_mrad: int, ranges_mm: list[int] | tuple[int, ...],
                      status: list[int] | tuple[int, ...], seen: set[tuple[int, int]]) -> list[tuple[int, int]]:
        """Points inside a sensor's cone nearer than its reading by `clear_margin_mm` (a too-far
        reading: nearer than the range's maximum): nothing is there any more. A cone reports its
        nearest echo, so anything in it nearer than the reading would have been read instead."""
        cfg = self.cfg
        lay, ang, mount, order = self.layout, self._ang, self._mount, self._order
        reach = lay.max_range_mm + mount
        th = heading_mrad / 1000.0
        out: list[tuple[int, int]] = []
        for key, (px, py, _) in self.points.items():
            if key in seen:
                continue
            dx, dy = px - x_mm, py - y_mm
            if abs(dx) > reach or abs(dy) > reach:
                continue
            rel = math.atan2(dy, dx) - th
            i = _nearest_sensor(rel, ang, order)
            st = status[i]
            if st == robot_spec.RANGE_VALID:
                r = ranges_mm[i]
            elif st == robot_spec.RANGE_TOO_FAR:
                r = lay.max_ranges_mm[i]
            else:
                continue
            a = th + ang[i]
            sx, sy = px - (x_mm + mount * math.cos(a)), py - (y_mm + mount * math.sin(a))
            d = math.hypot(sx, sy)
            off = abs((math.atan2(sy, sx) - a + math.pi) % (2 * math.pi) - math.pi)
            if off <= self._half_fov and d < r - cfg.clear_margin_mm:
                out.append(key)
        return out

    def _no_room(self, x_mm: int, y_mm: int, heading_mrad: int, ranges_mm: list[int] | tuple[int, ...],
                 status: list[int] | tuple[int, ...], skip: set[tuple[int, int]]) -> list[tuple[int, int]]:
        """Points near the rim where no body of `MIN_BODY_RADIUS_MM` could stand unseen (module
        docstring): every disc of that radius with the point on its edge either overlaps the robot or
        is crossed, `_BODY_SLACK_MM` deep, by a sensor's ray nearer than its reading by
        `clear_margin_mm` (the rays as the collision monitor's: each cone's middle and edges from the
        rim). A real body of that size or more keeps its points: the disc inside it through the
        point is crossed by no ray short of the body. Only points within 3 radii of the rim are
        looked at (farther out a disc fits in the gap between two cones of the built-in robot)."""
        lay, cfg = self.layout, self.cfg
        rim = float(lay.robot_radius_mm)
        rho = float(MIN_BODY_RADIUS_MM)
        reach = rim + 3 * rho
        pts = [(key, px - x_mm, py - y_mm) for key, (px, py, _) in self.points.items()
               if key not in skip and abs(px - x_mm) <= reach and abs(py - y_mm) <= reach]
        if not pts:
            return []
        th = heading_mrad / 1000.0
        segs: list[Segment] = []  # (start x, y, unit x, y, free length)
        for i, a in enumerate(self._ang):
            if status[i] == robot_spec.RANGE_VALID:
                free = ranges_mm[i] - cfg.clear_margin_mm
            elif status[i] == robot_spec.RANGE_TOO_FAR:
                free = lay.max_ranges_mm[i] - cfg.clear_margin_mm
            else:
                continue
            if free <= 0:
                continue
            for d in (-self._half_fov, 0.0, self._half_fov):
                c, s = math.cos(th + a + d), math.sin(th + a + d)
                segs.append((rim * c, rim * s, c, s, float(free)))
        if not segs:
            return []
        clear2, near2 = (rho - _BODY_SLACK_MM) ** 2, 4 * rho * rho  # near2: a ray within 2 rho reaches a disc
        inside2 = (rim + rho) ** 2  # a disc centre nearer the robot's than rim + rho overlaps its body
        out: list[tuple[int, int]] = []
        for key, px, py in pts:
            d = math.hypot(px, py)
            if d > reach or d == 0.0:
                continue
            near = _within(px, py, segs, near2)  # rays that can reach a disc on it
            if not near:
                continue
            # the disc beyond the point first (a body the robot reads lies there): most kept points stop at it
            for ux, uy in [(px / d, py / d), *_BODY_DIRS]:
                cx, cy = px + rho * ux, py + rho * uy
                if cx * cx + cy * cy >= inside2 and not _within(cx, cy, near, clear2, first=True):
                    break  # room for a body here
            else:
                out.append(key)
        return out

    def within(self, x: float, y: float, mm: float) -> bool:
        """A remembered point nearer than `mm` to (x, y)."""
        return any((px - x) ** 2 + (py - y) ** 2 < mm * mm for px, py, _ in self.points.values())

    def pin(self, now_us: int) -> None:
        """Keep every point remembered now for `route_memory_us` (a global re-plan goes round them)."""
        until = now_us + self.cfg.route_memory_us
        for p in self.points:
            self.pinned[p] = max(until, self.pinned.get(p, -1))

    def nearest(self, x: float, y: float) -> tuple[int, int] | None:
        """The remembered point nearest (x, y), or None."""
        return min(((qx, qy) for qx, qy, _ in self.points.values()), key=lambda q: (q[0] - x) ** 2 + (q[1] - y) ** 2,
                   default=None)

    def unpin_near(self, x: float, y: float, mm: float) -> None:
        """Points within `mm` of the point nearest (x, y) (the body standing there: a person) are kept
        `memory_us` like the others from now; farther ones stay pinned (a box closing another door)."""
        nearest = self.nearest(x, y)
        if nearest is None:
            return
        px, py = nearest
        for key, (qx, qy, _) in self.points.items():
            if (qx - px) ** 2 + (qy - py) ** 2 <= mm * mm:
                self.pinned.pop(key, None)

    def clear(self, now_us: int | None = None, x: float = 0.0, y: float = 0.0, around_mm: float = 0.0) -> None:
        """Forget everything (a recovery: what is really there is seen again on the next tick); given
        the time, a point a global re-plan pinned that is still pinned and lies `around_mm` or more
        from (x, y) is kept (nav2's clearing around the robot): what closed the whole map's routes out
        there, or the robot goes round again instead of saying "no route". Readings that see through
        one still clear it."""
        keep = {} if now_us is None else {
            p: v for p, v in self.points.items()
            if self.pinned.get(p, -1) >= now_us and (v[0] - x) ** 2 + (v[1] - y) ** 2 >= around_mm ** 2}
        if len(keep) != len(self.points):
            self.version += 1
        self.points = keep
        self.pinned = {p: self.pinned[p] for p in keep}
        self.born = {p: t for p, t in self.born.items() if p in keep}

    def snapshot(self, born: bool = False) -> ObstacleMemory:
        """A copy for the planner's worker (the tick goes on changing this one); `born`: with when each
        point was first seen (for `standing_by`: a whole-map search's question only, a copy less a tick)."""
        copy = ObstacleMemory(self.cfg, self.layout)
        copy.points, copy.born = dict(self.points), (dict(self.born) if born else {})
        copy.version = self.version
        return copy

    def seen_by(self, since_us: int) -> ObstacleMemory:
        """A copy holding only the points first seen by `since_us` (what came in since left out)."""
        copy = ObstacleMemory(self.cfg, self.layout)
        copy.points = {p: v for p, v in self.points.items() if self.born.get(p, since_us) <= since_us}
        copy.version = self.version
        return copy

    def standing_by(self, since_us: int) -> ObstacleMemory:
        """A copy holding only what stood still since `since_us`: the points first seen by then, less
        those within `body_mm` of a point first seen later (a body that showed new points moved: a mover
        shifting on the spot, not a box)."""
        new = [v for p, v in self.points.items() if self.born.get(p, since_us) > since_us]
        moved: set[tuple[int, int]] = set()
        body = self.body_mm
        k = body // _KEY_MM + 1
        for nx, ny, _ in new:
            cx, cy = nx // _KEY_MM, ny // _KEY_MM
            moved.update((cx + dx, cy + dy) for dx in range(-k, k + 1) for dy in range(-k, k + 1))
        copy = self.seen_by(since_us)
        copy.points = {p: v for p, v in copy.points.items() if not (
            p in moved and any((v[0] - nx) ** 2 + (v[1] - ny) ** 2 <= body * body for nx, ny, _ in new))}
        return copy
