"""Local re-planning round obstacles the map does not show (robot side).

The ground station plans waypoints on the known map; a box in a corridor or
a person walking past is not on it. This module owns what the robot does
about them before its learnt sector policy steers:

* `unmapped_ends` / `unmapped_readings` tell which range readings the map
  does not explain: on no ray of the sensor's fan (the sensor geometry of
  `robot_spec`, as the twin's `sense` casts it) does the point at the read
  distance lie within `margin_mm` of an occupied cell or the map's edge. A
  disc, a box or a person in the open is unmapped; a map wall never is,
  also from a pose a little off (the margin absorbs the localiser's ~0.1 m
  corridor error) and also where a fan ray grazes a corner. The ray end
  points are computed in floats and rounded to whole mm; the wall test is
  integers. The controller also withholds these readings from its
  localiser (`Controller._statuses_for_localiser`).
* `ObstacleMemory` keeps the end points of range readings the map does not
  explain, in world millimetres, one per 50 mm square, each stamped with the
  controller clock (sim time in HIL) and forgotten `memory_us` after it was
  last seen: a person who walked on leaves no wall behind, a box in view is
  seen again every tick. A reading clears the points inside its cone that
  lie nearer than it by `clear_margin_mm` (nav2's obstacle layer clears by
  raytracing: a cone reports its nearest echo), so a
  mover that stepped aside is gone at once; points the robot is going
  round, and points pinned by a global re-plan, are kept
  `route_memory_us` (a door found closed stays closed while the robot goes
  round through another) unless a reading sees through them.
* `LocalPlanner.target(x, y, waypoint, memory)` is the point the policy
  steers to. While no remembered point comes within `obstacle_clear_mm` of
  the straight line to the waypoint it is the waypoint itself, so on the
  known map the policy drives exactly as trained. Once one does (for this
  waypoint: `reset()` per mission item), the planner runs Dijkstra on a
  `raster_mm` raster of a window round the robot and the waypoint: map
  walls grown by `wall_clear_mm` and remembered points grown by
  `obstacle_clear_mm` are closed, and cells within `soft_mm` of a point
  cost up to `weight` times more (nav2's inflation cost: the path keeps its
  distance where there is room and squeezes through where there is not).
  The target is then the furthest cell, within `lookahead_mm` along the
  path, that the robot sees in a straight line keeping `los_clear_mm` from
  every point, or the waypoint itself when that line is clear. The learnt
  policy was trained to reach a point it can see with walls beside its
  line; the planner hands it such points.

* When the window's search finds no way from the robot to the waypoint,
  `PlannedTarget` runs the recoveries, in order: wait (a mover may step
  aside), re-plan over the whole map round the pinned points (another
  door, another aisle: followed like a local detour), and when there is no
  route: when something came up to the robot while it waited (a person who
  will not give way, standing at it) give way first: drive to the nearest
  place off the line that body walks (`LocalPlanner.refuge`: a side
  corridor behind the robot, a room's corner) and stand there until the
  way opens, then back to the waypoint by the whole map's route; otherwise
  (or with nowhere to stand aside) back off, clear the obstacle layer
  round the robot (what closed the route farther away is kept while
  pinned), wait longer and re-plan again; after `max_rounds` global
  searches without a route it says "no route" (`PlannedTarget.no_route`),
  and the controller reports it (STATUSTEXT, severity error) and ends the
  mission in HOLD.

* `MotionGuard.action(...)` has the last word on the table's action (as
  nav2's collision monitor and back-up recovery do for its controllers): a
  forward step is replaced by a turn toward the target while the front or
  a front diagonal sensor reads nearer than `veto_mm` (a round robot
  turning in place touches nothing), and a robot that has not moved
  `stuck_mm` for `stuck_us` with a remembered point within its radius +
  `backoff_near_mm` backs off for `backoff_us` if the rear sensors are
  clear (checked every tick of it, which also ends when a side reading
  falls to `veto_mm` or under: something closing in beside the robot): a
  person pinned between a wall and the robot can then step aside. A
  forward step the collision monitor has held `HELD_TURN_US` is turned
  toward the target, as a veto.
  A turn in place toward a target behind the robot (more than
  `TURN_COMMIT_MRAD` off the heading) is kept the way it began: the
  table's bearing sectors meet behind the robot, and one turn step there
  flips the target to the other side, so the table turned left, right,
  left for good (squeezed between two discs and a wall: 20 s on the spot).
  Nearer ahead, after `DITHER_REVERSALS` reversals in a row the guard
  steps forward when the front sensors read at least twice `veto_mm` (a
  target just off ahead, a wall close on one diagonal: the table turned
  to and fro between two headings for good).
  A body the map does not explain (the obstacle memory holds it that
  near) touching the flank or a front diagonal ahead of the axle (a mover
  that walked up to the robot and stands while it would overlap it) is
  turned away from, the same way whatever the table asks, until a step
  ahead is clear by `collision.travel_gap_mm`, then `ESCAPE_STEPS` steps
  are taken ahead (`MotionGuard._escape`): the table, or the front veto
  turning toward a target on the body's side, turned into it and back on
  the spot while the collision monitor held every step (the no-yield
  bench's loops), or, before the monitor knew the blind gaps, stepped
  into it (all its 14 collisions). A reverse the monitor holds
  `HELD_TURN_US` is turned toward the target as a held forward step is.

* `PlannedTarget` is the tick's side of the planner: the search does not
  run in the control tick (issue 29 finding 4: legal metadata made one
  tick take 1 s). Each tick it remembers what it sees, decides whether
  anything is in the way (cheap), posts the question (pose, waypoint, a
  copy of the memory) to `firmware_py.background`, and steers by the
  latest answer: at full speed while that answer (or, before the first,
  the moment the way became blocked) is at most `PLAN_SLOW_US` old on the
  controller clock, at half speed after that, and not at all once it is
  `PLAN_STOP_US` old. On the robot the answer comes from a worker thread; in lockstep HIL
  and in the twin the search runs between two ticks, so the answer of tick
  k is used from tick k+1 and runs stay reproducible.

The work is bounded: the raster window is at most (`max_plan_mm` + 2 x
`window_mm`) square and at most `MAX_WINDOW_CELLS` raster cells a side
(farther waypoints are driven at without planning until they are near
enough), Dijkstra runs again only when the remembered set or the waypoint
changes, and memory holds at most `max_points` points (the oldest go
first). Pure stdlib (the robot has no numpy); the twin's bench runs this
same code.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, fields
from typing import Any

from firmware_py import robot_spec
from firmware_py.background import Background
from firmware_py.control import collision
from firmware_py.mapdata import OccupancyGrid

META_KEY = "local_planner"  # policy metadata: the planner's parameters (an object; {} = the defaults)
_KEY_MM = 50  # one remembered point per 50 mm square
_SQRT2 = 1.4142
_UNKNOWN = 2  # a raster cell of the map's configuration space not computed yet
MAX_WINDOW_CELLS = 200  # raster cells a side of the search window (40,000 cells, ~0.3 s of search)
PLAN_SLOW_US = 300_000  # an answer older than this (controller clock): half speed ...
PLAN_STOP_US = 1_000_000  # ... and none this old (or none for this long): stop

# the sensor fans of robot_spec, for `unmapped_ends` (the twin's `sense` casts the same rays)
_N = robot_spec.SENSOR_COUNT
_ANG = [a / 1000.0 for a in robot_spec.SENSOR_ANGLES_MRAD]
_SENS_COS = [math.cos(a) for a in _ANG]
_SENS_SIN = [math.sin(a) for a in _ANG]
_FAN = ([(k / (robot_spec.SENSOR_FAN_RAYS - 1) - 0.5) * (robot_spec.SENSOR_FOV_MRAD / 1000.0)
         for k in range(robot_spec.SENSOR_FAN_RAYS)] if robot_spec.SENSOR_FAN_RAYS > 1 else [0.0])
_RAY_COS = [[math.cos(a + f) for f in _FAN] for a in _ANG]
_RAY_SIN = [[math.sin(a + f) for f in _FAN] for a in _ANG]
_MOUNT = float(robot_spec.SENSOR_MOUNT_RADIUS_MM)
_HALF_FOV = robot_spec.SENSOR_FOV_MRAD / 2000.0


def _walls_near(grid: OccupancyGrid, x: int, y: int, m: int) -> Iterator[tuple[int, int]]:
    """(dx, dy) mm from the point (x, y) to each occupied cell (or the outside of the grid: the
    world's outer walls) whose square may lie within m mm (integers only; 0 along an axis inside)."""
    c = grid.cell_mm
    top = grid.height * c
    for row in range((top - (y + m)) // c, (top - (y - m)) // c + 1):
        ylo = top - (row + 1) * c
        dy = ylo - y if y < ylo else (y - ylo - c if y > ylo + c else 0)
        for col in range((x - m) // c, (x + m) // c + 1):
            if grid.occupied(col, row):
                xlo = col * c
                yield (xlo - x if x < xlo else (x - xlo - c if x > xlo + c else 0)), dy


def _wall_within(grid: OccupancyGrid, x: int, y: int, m: int) -> bool:
    """An occupied cell (or the outside of the grid) has a point within m mm of the point (x, y) mm."""
    return any(dx * dx + dy * dy <= m * m for dx, dy in _walls_near(grid, x, y, m))


def _wall_gap(grid: OccupancyGrid, x: int, y: int, m: int) -> float:
    """Distance (mm) from the point to the nearest occupied cell (or the outside of the grid), capped at m."""
    return min([float(m), *(math.hypot(dx, dy) for dx, dy in _walls_near(grid, x, y, m))])


MAP_MARGIN_MM = 150  # a reading is explained by the map within this distance of a mapped cell
# ObstacleMemory.added counts new points this near the robot: a person walking to and fro a metre off
# a disc that closes the only door made every round of recoveries a "moving scene" (at window_mm, 1 m),
# and the robot waited until its time ran out instead of saying "no route"
MOVING_NEAR_MM = 700
# a moving scene's new points belong to a body that moved: remembered points this near one of them are
# that body's (a person is about the robot's width; ObstacleMemory.standing_by)
BODY_MM = 2 * robot_spec.ROBOT_RADIUS_MM
# giving way (LocalPlanner.refuge): the robot stands this far off the line a person walks (two radii
# and a margin: a person walking a 500 mm corridor is up to 100 mm off its middle) ...
REFUGE_MM = 2 * robot_spec.ROBOT_RADIUS_MM + 150
REFUGE_SEARCH_MM = 2500  # ... at a place at most this far along the way


def unmapped_ends(grid: OccupancyGrid, x_mm: int, y_mm: int, heading_mrad: int,
                  ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
                  margin_mm: int, max_mm: int = robot_spec.RANGE_MAX_MM) -> list[tuple[int, int, int, int]]:
    """(sensor, distance mm, x, y) per reading the map does not explain, the
    point being the end of the fan's middle ray. A reading is explained when,
    on any ray of the sensor's fan, the point at the read distance (rounded
    to whole mm) lies within margin_mm of an occupied cell or the map's edge;
    too far and invalid readings, and readings beyond max_mm, never count
    (nothing seen); a too-close reading is taken at the range's minimum."""
    out: list[tuple[int, int, int, int]] = []
    th = heading_mrad / 1000.0
    ct = math.cos(th)
    st = math.sin(th)
    mid = len(_FAN) // 2
    for i in range(_N):
        if status[i] == robot_spec.RANGE_TOO_CLOSE:
            r = robot_spec.RANGE_MIN_MM
        elif status[i] == robot_spec.RANGE_VALID:
            r = ranges_mm[i]
        else:
            continue
        if r > max_mm:
            continue
        ox = x_mm + _MOUNT * (ct * _SENS_COS[i] - st * _SENS_SIN[i])
        oy = y_mm + _MOUNT * (st * _SENS_COS[i] + ct * _SENS_SIN[i])
        explained = False
        end = (0, 0)
        for k in range(len(_FAN)):
            cx = ct * _RAY_COS[i][k] - st * _RAY_SIN[i][k]
            cy = st * _RAY_COS[i][k] + ct * _RAY_SIN[i][k]
            ex, ey = math.floor(ox + r * cx + 0.5), math.floor(oy + r * cy + 0.5)
            if _wall_within(grid, ex, ey, margin_mm):
                explained = True
                break
            if k == mid:
                end = (ex, ey)
        if not explained:
            out.append((i, r, end[0], end[1]))
    return out


def unmapped_readings(grid: OccupancyGrid, x_mm: int, y_mm: int, heading_mrad: int,
                      ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
                      margin_mm: int) -> list[int]:
    """Per sensor: its distance (mm) when the map does not explain the
    reading (`unmapped_ends`; too close: 0), else -1."""
    out = [-1] * _N
    for i, r, _, _ in unmapped_ends(grid, x_mm, y_mm, heading_mrad, ranges_mm, status, margin_mm):
        out[i] = 0 if status[i] == robot_spec.RANGE_TOO_CLOSE else r
    return out


def mapped_readings(grid: OccupancyGrid, pose_mm: tuple[int, int, int], ranges_mm: list[int] | tuple[int, ...],
                    status: list[int] | tuple[int, ...], margin_mm: int = MAP_MARGIN_MM) -> list[bool]:
    """Per sensor: the map explains its reading at this pose (`unmapped_ends`); a too-far or
    invalid reading is not a reading (False). The collision monitor's `mapped`, which it reads only
    for a reading under CONTACT_MM: with none, [] (the map is not asked; the controller's tick and
    the twin's hot loop are spared it)."""
    if not collision.touching(ranges_mm, status):
        return []
    x, y, heading = pose_mm
    unmapped = unmapped_readings(grid, x, y, heading, ranges_mm, status, margin_mm)
    return [u < 0 and status[i] in (robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_CLOSE)
            for i, u in enumerate(unmapped)]


@dataclass(frozen=True)
class LocalPlannerConfig:
    """The planner's parameters (mm, us); `from_metadata` checks each."""

    margin_mm: int = MAP_MARGIN_MM
    see_mm: int = 1500  # readings farther than this are not remembered (the fan is wide out there)
    memory_us: int = 3_000_000  # a point not seen again for this long is forgotten
    max_points: int = 400
    raster_mm: int = 100
    wall_clear_mm: int = robot_spec.ROBOT_RADIUS_MM + 25
    obstacle_clear_mm: int = robot_spec.ROBOT_RADIUS_MM + 40
    soft_mm: int = robot_spec.ROBOT_RADIUS_MM + 200
    weight: int = 3
    los_clear_mm: int = robot_spec.ROBOT_RADIUS_MM + 100
    window_mm: int = 1000
    lookahead_mm: int = 600
    max_plan_mm: int = 3000  # no planning toward a waypoint farther than this (bounds the tick's work)
    # the motion guard (MotionGuard): no forward step into a reading this near ...
    veto_mm: int = 40
    # ... and backing off when the robot has not moved stuck_mm for stuck_us next to a remembered point
    stuck_mm: int = 50
    stuck_us: int = 2_000_000
    backoff_us: int = 500_000
    backoff_near_mm: int = 100  # the point within robot radius + this
    rear_clear_mm: int = 250  # the rear sensor must read at least this ...
    rear_side_clear_mm: int = 120  # ... and the rear diagonals at least this
    # a reading this much longer than the distance to a remembered point inside its cone clears the
    # point (nav2's obstacle layer clears by raytracing: a mover that walked on leaves no wall behind)
    clear_margin_mm: int = 150
    # recoveries when the local route is closed (Recovery): stand still this long for a mover ...
    wait_us: int = 2_000_000
    # ... the points that closed it are kept this long (unless a reading sees through them) while the
    # robot re-plans globally round them, so a detour through another door does not turn back ...
    route_memory_us: int = 60_000_000
    # ... and after this many global re-plans without a route: "no route" (round r waits r x wait_us:
    # a mover in the only corridor walks off in a few seconds, a box in a door stays)
    max_rounds: int = 3
    # a round whose wait saw more new points than this was a moving scene (a mover in the only way):
    # it does not count toward "no route" (at most 3 x max_rounds rounds in all)
    moving_points: int = 8

    @classmethod
    def from_metadata(cls, meta: Any) -> LocalPlannerConfig:
        """The config in a policy's metadata value; ValueError with one line naming the bad field."""
        if not isinstance(meta, dict):
            raise ValueError(f"{META_KEY} is not a JSON object")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(meta) - known)
        if unknown:
            raise ValueError(f"{META_KEY}: unknown field {unknown[0]!r}")
        for k, v in meta.items():
            if not isinstance(v, int) or isinstance(v, bool) or not 0 < v <= 100_000_000:
                raise ValueError(f"{META_KEY}.{k} = {v!r} is not a positive integer")
        cfg = cls(**meta)
        if not 50 <= cfg.raster_mm <= 500:
            raise ValueError(f"{META_KEY}.raster_mm = {cfg.raster_mm} (allowed 50..500)")
        for name in ("margin_mm", "wall_clear_mm", "obstacle_clear_mm"):  # bound the per-point work
            if getattr(cfg, name) > 1000:
                raise ValueError(f"{META_KEY}.{name} = {getattr(cfg, name)} (allowed up to 1000)")
        if not cfg.obstacle_clear_mm <= cfg.los_clear_mm <= cfg.soft_mm:
            raise ValueError(f"{META_KEY}: need obstacle_clear_mm <= los_clear_mm <= soft_mm")
        if cfg.backoff_us >= cfg.stuck_us:
            raise ValueError(f"{META_KEY}: need backoff_us < stuck_us")
        if (cfg.max_points > 1000 or cfg.window_mm > 5000 or cfg.soft_mm > 2000 or cfg.max_plan_mm > 10_000
                or cfg.lookahead_mm > 5000):
            raise ValueError(f"{META_KEY}: max_points <= 1000, window_mm <= 5000, soft_mm <= 2000, "
                             "max_plan_mm <= 10000 and lookahead_mm <= 5000")
        if cfg.max_rounds > 10 or cfg.clear_margin_mm > 1000 or cfg.wait_us > 30_000_000:
            raise ValueError(f"{META_KEY}: max_rounds <= 10, clear_margin_mm <= 1000 and wait_us <= 30000000")
        if cfg.soft_mm // cfg.raster_mm > 5:  # each point grows into (2 k + 3)^2 raster cells
            raise ValueError(f"{META_KEY}: soft_mm is more than 5 raster cells ({cfg.soft_mm} / {cfg.raster_mm})")
        side = (cfg.max_plan_mm + 2 * cfg.window_mm) // cfg.raster_mm
        if side > MAX_WINDOW_CELLS:  # the search's size in cells, whatever the millimetres say
            raise ValueError(f"{META_KEY}: the search window is {side} raster cells a side "
                             f"((max_plan_mm + 2 window_mm) / raster_mm; allowed up to {MAX_WINDOW_CELLS})")
        return cfg

    def to_metadata(self) -> dict[str, int]:
        return asdict(self)


class ObstacleMemory:
    """Unmapped reading end points (world mm) with the time each was last seen, cleared by readings
    that see through them; points pinned by a global re-plan outlive `memory_us` (module docstring)."""

    def __init__(self, cfg: LocalPlannerConfig) -> None:
        self.cfg = cfg
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
                                          cfg.see_mm):
            key = (ex // _KEY_MM, ey // _KEY_MM)
            if key not in self.points:
                self.version += 1
                self.added += (ex - x_mm) ** 2 + (ey - y_mm) ** 2 <= near
                self.born[key] = now_us
            self.points[key] = (ex, ey, now_us)
            seen.add(key)
        old = self._seen_through(x_mm, y_mm, heading_mrad, ranges_mm, status, seen)
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
        if old:
            self.version += 1

    def _seen_through(self, x_mm: int, y_mm: int, heading_mrad: int, ranges_mm: list[int] | tuple[int, ...],
                      status: list[int] | tuple[int, ...], seen: set[tuple[int, int]]) -> list[tuple[int, int]]:
        """Points inside a sensor's cone nearer than its reading by `clear_margin_mm` (a too-far
        reading: nearer than the range's maximum): nothing is there any more. A cone reports its
        nearest echo, so anything in it nearer than the reading would have been read instead.
        (Tried: clearing only along the simulated fan's 3 rays, as a small disc between two rays
        goes unseen: 0.968 -> 0.943 on the bench, mover trails kept blocking routes.)"""
        cfg = self.cfg
        reach = robot_spec.RANGE_MAX_MM + _MOUNT
        th = heading_mrad / 1000.0
        out: list[tuple[int, int]] = []
        for key, (px, py, _) in self.points.items():
            if key in seen:
                continue
            dx, dy = px - x_mm, py - y_mm
            if abs(dx) > reach or abs(dy) > reach:
                continue
            rel = math.atan2(dy, dx) - th
            i = min(range(_N), key=lambda j: abs((rel - _ANG[j] + math.pi) % (2 * math.pi) - math.pi))
            st = status[i]
            if st == robot_spec.RANGE_VALID:
                r = ranges_mm[i]
            elif st == robot_spec.RANGE_TOO_FAR:
                r = robot_spec.RANGE_MAX_MM
            else:
                continue
            a = th + _ANG[i]
            sx, sy = px - (x_mm + _MOUNT * math.cos(a)), py - (y_mm + _MOUNT * math.sin(a))
            d = math.hypot(sx, sy)
            off = abs((math.atan2(sy, sx) - a + math.pi) % (2 * math.pi) - math.pi)
            if off <= _HALF_FOV and d < r - cfg.clear_margin_mm:
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
        if not self.points:
            return None
        return min(((qx, qy) for qx, qy, _ in self.points.values()), key=lambda q: (q[0] - x) ** 2 + (q[1] - y) ** 2)

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
        there (a box seen from one side, the robot gone round to find it from the other: forgetting
        it sent the robot round again instead of saying "no route"). Readings that see through one
        still clear it."""
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
        copy = ObstacleMemory(self.cfg)
        copy.points = dict(self.points)
        if born:
            copy.born = dict(self.born)
        copy.version = self.version
        return copy

    def standing_by(self, since_us: int) -> ObstacleMemory:
        """A copy holding only what stood still since `since_us`: the points first seen by then, less
        those within `BODY_MM` of a point first seen later (a body that showed new points moved: a mover
        shifting on the spot, not a box)."""
        new = [v for p, v in self.points.items() if self.born.get(p, since_us) > since_us]
        moved: set[tuple[int, int]] = set()
        k = BODY_MM // _KEY_MM + 1
        for nx, ny, _ in new:
            cx, cy = nx // _KEY_MM, ny // _KEY_MM
            moved.update((cx + dx, cy + dy) for dx in range(-k, k + 1) for dy in range(-k, k + 1))
        copy = ObstacleMemory(self.cfg)
        copy.points = {p: v for p, v in self.points.items() if self.born.get(p, since_us) <= since_us and not (
            p in moved and any((v[0] - nx) ** 2 + (v[1] - ny) ** 2 <= BODY_MM * BODY_MM for nx, ny, _ in new))}
        copy.version = self.version
        return copy


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

    def __init__(self, grid: OccupancyGrid, cfg: LocalPlannerConfig) -> None:
        self.grid = grid
        self.cfg = cfg
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
        other = LocalPlanner(self.grid, self.cfg)
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
            d = _wall_gap(self.grid, ix * r + r // 2, iy * r + r // 2, cfg.soft_mm)
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
            v = 0 if _wall_within(self.grid, ix * r + r // 2, iy * r + r // 2, self.cfg.wall_clear_mm) else 1
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
        m = robot_spec.ROBOT_RADIUS_MM + 10
        along = 25.0
        while along <= min(length, 175.0):
            if _wall_within(self.grid, round(x + along * ux), round(y + along * uy), m):
                return False
            along += 25.0
        return True

    # --- the plan --------------------------------------------------------------------------------
    def _plan(self, x: float, y: float, wx: int, wy: int, version: int, whole_map: bool = False,
              asked_us: int = 0) -> None:
        """Dijkstra from the waypoint over a window round the robot and the waypoint (`whole_map`:
        over the whole map, a global re-plan), unless the last search still holds. A whole-map route
        the robot is on, closed ahead by points seen since, is held to for `wait_us` (`held`: the robot
        stands) before the search runs again: a mover walking across it closed it, the next search
        sent the robot the other way round, the mover closed that, and the robot went to and fro
        between two doors (issue 32: most of the twin's remaining loops)."""
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

    def _route_length(self, cur: Cell, max_steps: int = 4000) -> float:
        """Length (mm) of the last search's way from raster cell `cur` down to the waypoint (the
        distances are costs, inflation included: the way is walked to measure it)."""
        dist, r = self._dist, self.cfg.raster_mm
        c, total = cur, 0.0
        for _ in range(max_steps):
            d, nxt = min((dist.get((c[0] + dx, c[1] + dy), math.inf), (c[0] + dx, c[1] + dy))
                         for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy)
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
            d, nxt = min((dist.get((c[0] + dx, c[1] + dy), math.inf), (c[0] + dx, c[1] + dy))
                         for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy)
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
            d, nxt = min((dist.get((c[0] + dx, c[1] + dy), math.inf), (c[0] + dx, c[1] + dy))
                         for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy)
            if d >= dist[c]:
                break
            path.append(nxt)
        # the whole map's route passes doors and corners of the map: every target there is one the
        # robot sees in a straight line (a window's detour goes round points in the open)
        best = path[0]
        if not whole_map and len(path) > 1 and self._body_clear(x, y, path[1][0] * r + r / 2, path[1][1] * r + r / 2):
            best = path[1]  # a window's detour: the next cell unless the body would clip a wall toward it
        for c in path[1 if whole_map else 2:]:  # the furthest the robot sees (not the last before one it
            if self._line_clear(x, y, c[0] * r + r / 2, c[1] * r + r / 2, memory):  # does not: a path
                best = c  # bending round a point hides its next cells and shows the ones after them)
        if best == path[0] and len(path) > 1 and self._body_clear(x, y, path[1][0] * r + r / 2,
                                                                  path[1][1] * r + r / 2):
            # a route squeezing between a point and a wall nearer than los_clear_mm (it is open at
            # obstacle_clear_mm): none of its cells is in plain sight, and steering to the robot's own
            # cell held it there for good; the next cell, as a window's detour takes it
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
                                            robot_spec.ROBOT_RADIUS_MM + 10)
                and self._body_clear(x, y, c[0] * r + r / 2, c[1] * r + r / 2)]

    def refuge(self, x: float, y: float, memory: ObstacleMemory) -> tuple[int, int] | None:
        """Where to stand aside for the body nearest the robot (a person who does not give way,
        walking at it down a one-cell corridor), or None: the raster cell nearest by way (Dijkstra
        over the map's free space, the remembered points grown, up to `REFUGE_SEARCH_MM`) whose
        centre lies `REFUGE_MM` or more off the line the body walks (through the robot, along the grid
        axis nearest the direction from the body to the robot: on an occupancy grid a corridor runs
        along an axis, and a person walking in one is rarely in its middle, so the direction between
        the two is up to ~20 degrees off it) and `REFUGE_MM` or more from the body: a side corridor or
        a room's corner it walks past."""
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
        while heap:
            d, c = heapq.heappop(heap)
            if d > dist[c] or d > limit:
                continue
            cx, cy = c[0] * r + r / 2, c[1] * r + r / 2
            if (abs((cx - x) * uy - (cy - y) * ux) >= REFUGE_MM
                    and (cx - px) ** 2 + (cy - py) ** 2 >= REFUGE_MM ** 2):
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


@dataclass(frozen=True)
class PlanAnswer:
    """The worker's answer to one question: where to steer from the pose asked about."""

    generation: int  # PlannedTarget.reset() count when asked (older answers are for another waypoint)
    waypoint: tuple[int, int]
    asked_us: int  # the controller clock at the question
    target: tuple[float, float]
    detouring: bool
    whole_map: bool = False  # a global re-plan's answer
    blocked: bool = False  # no way from the pose to the waypoint (in the window searched)
    no_route: bool = False  # none over the whole map either
    route_mm: float = 0.0  # the planned way's length from the pose asked about
    held: bool = False  # the whole map's route is closed ahead: stand while it is held to
    refuge: tuple[int, int] | None = None  # with no_route: where to stand aside (LocalPlanner.refuge)
    # with no_route: none either over what stood still through the round's wait (ObstacleMemory.standing_by):
    # what moved did not close the way
    still_closed: bool = False


@dataclass(frozen=True)
class RefugeAnswer:
    """The worker's answer while the robot gives way: where to steer now on the way to the refuge."""

    generation: int
    asked_us: int
    target: tuple[float, float]


# PlannedTarget's recovery modes, in the order they follow one another (see PlannedTarget)
LOCAL, WAIT, GLOBAL, GIVE_WAY, BACKUP, CLEAR, NO_ROUTE = (
    "local", "wait", "global", "give way", "backup", "clear", "no route")
ROUTE_SWITCH_MM = 1000  # a whole-map answer this much longer than the route followed is another route
GIVE_WAY_US = 15_000_000  # at most this long driving to the place where the robot stands aside
REFUGE_REACHED_MM = 100  # ... which it has reached this near


class PlannedTarget:
    """The tick's side of the local planner (module docstring): one per drive of a sector policy.

    Recoveries, when the window's search finds no way to the waypoint (nav2's recovery behaviours,
    in this order, all on the controller clock):

    1. WAIT `wait_us` (in round r, r x `wait_us`), stopped: a mover may step aside (a reading that
       sees through a remembered point clears it); the window's search goes on, and a way found
       ends the recovery.
    2. GLOBAL: the points remembered now are pinned (`route_memory_us`) and the search covers the
       whole map: another door, another aisle. A route is followed to the waypoint (the search
       runs again when the way ahead closes).
    3. No route: BACKUP `backoff_us` (the driver reverses when the rear is clear), CLEAR the
       obstacle layer round the robot (what is really there is seen again next tick; pinned points
       `window_mm` or more away stay while pinned: what closed the whole map's routes out there),
       then 1. again. In a round where something came up to the robot (below), GIVE_WAY first:
       the robot drives to the nearest place off the line the nearest body walks
       (`LocalPlanner.refuge`: a side corridor behind it, a room's corner) and stands there (1.
       again: the wait's search ends it once the way is open, and the way back is the whole map's
       route), as a person in a one-cell corridor steps into a side door for someone who will not;
       with no such place within `REFUGE_SEARCH_MM`, BACKUP. A drive there is at most
       `GIVE_WAY_US`; the round spent standing aside does not count.
    4. After `max_rounds` global searches without a route: NO_ROUTE, stopped, `no_route` says why
       (the controller reports it and ends the mission). A round whose wait saw more than
       `moving_points` new points within `MOVING_NEAR_MM`, and whose whole map would be open without
       what moved since its wait began (the points first seen since, and older ones of the same
       bodies: `ObstacleMemory.standing_by`), was a moving scene (a mover walking in the only way,
       not one walking past a box that closes it) and does not count, up to 3 x `max_rounds` rounds
       in all; nor does one in which a remembered point came within the robot's radius + `veto_mm`
       (the guard never steps that close: it came to the robot, a person who will not give way
       standing at it in a one-cell corridor).

    A waypoint beyond `max_plan_mm` is driven at without planning while the map leaves the straight
    line to it free (looked at off the tick); once it does not (a recovery's detour left the route
    the waypoints follow) the tick's side goes to GLOBAL at once: the whole map's route leads back.
    """

    def __init__(self, grid: OccupancyGrid, cfg: LocalPlannerConfig, work: Background) -> None:
        self.cfg = cfg
        self.planner = LocalPlanner(grid, cfg)  # used by the worker only, after construction
        self.work = work
        self._generation = 0
        self._worker_generation = 0
        self._answer: PlanAnswer | None = None
        self._active: tuple[int, int] | None = None
        self._active_since_us = 0
        self.detouring = False  # the last target was not the waypoint
        self.stale_ticks = 0  # ticks steered at reduced speed or stopped for want of a recent answer
        self.mode = LOCAL
        self._mode_since_us = 0
        self._rounds = 0  # global searches without a route for this waypoint (in a still scene)
        self._all_rounds = 0  # ... and in all
        self._added_at_wait = 0  # memory.added when the last wait began ...
        self._round_since_us = 0  # ... and when (the points first seen since moved in during the round)
        self._still_planner: LocalPlanner | None = None  # the worker's, for PlanAnswer.still_closed
        self._came_up = False  # something came up to the robot during this round (_recovering)
        self.reverse = False  # this tick: back off (BACKUP)
        self.no_route = ""  # why the waypoint cannot be reached (NO_ROUTE), else ""
        self._refuge: tuple[int, int] = (0, 0)  # where the robot stands aside (GIVE_WAY)
        self._refuge_answer: RefugeAnswer | None = None  # the worker's, while giving way
        self.give_ways = 0  # times the robot stood aside (telemetry / benchmarks)
        self._aside = False  # it stands aside now: off the route the waypoints follow (_recovering)
        self.global_plans = 0  # global re-plans started (telemetry / benchmarks)
        # whole-map routes taken: the first answer of a round with a route, and each switch to a way
        # round longer by ROUTE_SWITCH_MM (the route followed closed; benchmarks count progress anew)
        self.routes_taken = 0
        self._followed_mm = 0.0  # the whole-map route's length at the last answer followed
        self._round_taken = 0
        self.route_mm = 0.0  # the latest answer's planned way to the waypoint (benchmarks' progress)
        # (generation, waypoint, the map leaves the line to it free): a far waypoint's sight line (_look)
        self._far_sight: tuple[int, tuple[int, int], bool] | None = None

    @property
    def plans(self) -> int:
        return self.planner.plans + (self._still_planner.plans if self._still_planner is not None else 0)

    def reset(self) -> None:
        """A new waypoint (mission item): drive straight until something is in the way."""
        self._generation += 1
        self._answer = None
        self._active = None
        self.detouring = False
        self.mode, self._rounds, self._all_rounds, self.reverse, self.no_route = LOCAL, 0, 0, False, ""
        self._aside = False

    def _enter(self, mode: str, now_us: int) -> None:
        self.mode, self._mode_since_us = mode, now_us

    def _begin_round(self, now_us: int, memory: ObstacleMemory, came_up: bool) -> None:
        """A round of recoveries begins with its wait: what is added from now tells a moving scene."""
        self._added_at_wait, self._round_since_us, self._came_up = memory.added, now_us, came_up

    def target(self, now_us: int, x: float, y: float, waypoint: tuple[int, int],
               memory: ObstacleMemory) -> tuple[float, float, int]:
        """(x, y) mm to steer to this tick and the speed in percent (100, 50 or 0)."""
        wx, wy = waypoint
        self.reverse = False
        if self.mode == NO_ROUTE:
            return float(wx), float(wy), 0
        if self.mode == GIVE_WAY:
            return self._giving_way(now_us, x, y, waypoint, memory)
        if self.mode == BACKUP:
            if now_us - self._mode_since_us < self.cfg.backoff_us:
                self.reverse = True
                return float(wx), float(wy), 0
            memory.clear(now_us, x, y, self.cfg.window_mm)  # CLEAR: the next tick asks on what is seen again
            self._enter(CLEAR, now_us)
            return float(wx), float(wy), 0
        if self.mode == CLEAR:
            self._enter(WAIT, now_us)
            self._begin_round(now_us, memory, False)
        whole_map = self.mode == GLOBAL
        if not whole_map:  # in GLOBAL it stays the route's (a tick without an answer followed: the last one's)
            self.route_mm = math.hypot(wx - x, wy - y)
        if self.mode == LOCAL:
            if math.hypot(wx - x, wy - y) > self.cfg.max_plan_mm:
                self.detouring = False  # far: driven at without planning (LocalPlanner.target) ...
                gen = self._generation
                sight = self._far_sight
                if sight is not None and sight[:2] == (gen, waypoint) and not sight[2]:
                    # ... unless the map's walls stand between: a recovery's detour left the route the
                    # waypoints follow, and a straight drive at a waypoint metres away in a maze stalls
                    # at the first wall; the whole map's route leads back (issue 32)
                    memory.pin(now_us)
                    self.global_plans += 1
                    self._enter(GLOBAL, now_us + 1)
                    return float(wx), float(wy), 0
                self.work.post(self, lambda: self._look(gen, x, y, waypoint))
                return float(wx), float(wy), 100
            if self._active != waypoint:
                if not memory.points or not self.planner._in_way(x, y, wx, wy, memory):
                    self.detouring = False
                    return float(wx), float(wy), 100
                self._active, self._active_since_us = waypoint, now_us
            # what the robot goes round is kept while it does (unless a reading sees through it): a
            # box forgotten once out of view sent the route back to it, and the robot turned to and fro
            memory.pin(now_us)
        gen, snap, since = self._generation, memory.snapshot(born=whole_map), self._round_since_us
        self.work.post(self, lambda: self._solve(gen, now_us, x, y, waypoint, snap, whole_map, since))
        ans = self._answer
        if ans is not None and (ans.generation != gen or ans.waypoint != waypoint):
            ans = None
        if ans is not None and (ans.whole_map != whole_map or ans.asked_us < self._mode_since_us):
            ans = None  # asked before this mode began: not an answer to its question
        if self.mode in (WAIT, GLOBAL):
            if self.mode == WAIT and not self._came_up:
                self._came_up = memory.within(x, y, robot_spec.ROBOT_RADIUS_MM + self.cfg.veto_mm)
            return self._recovering(now_us, x, y, waypoint, ans, memory)
        if ans is not None and ans.blocked:
            self._enter(WAIT, now_us)
            self._begin_round(now_us, memory, False)
            return float(wx), float(wy), 0
        if ans is None:
            # nothing answered for this waypoint yet (the tick it became blocked, in lockstep and the
            # twin): toward it, the motion guard still vetoing; how long counts from then
            self.detouring = False
            age, tx, ty = now_us - self._active_since_us, float(wx), float(wy)
        else:
            self.detouring = ans.detouring
            age, (tx, ty) = now_us - ans.asked_us, ans.target
            self.route_mm = ans.route_mm
        return tx, ty, self._speed(age)

    def _speed(self, age_us: int) -> int:
        """Full speed while the answer steered by is at most PLAN_SLOW_US old, half up to PLAN_STOP_US,
        then none (counted as stale ticks)."""
        speed = 100 if age_us <= PLAN_SLOW_US else 50 if age_us <= PLAN_STOP_US else 0
        if speed < 100:
            self.stale_ticks += 1
        return speed

    def _recovering(self, now_us: int, x: float, y: float, waypoint: tuple[int, int], ans: PlanAnswer | None,
                    memory: ObstacleMemory) -> tuple[float, float, int]:
        """WAIT and GLOBAL (the class docstring's steps 1, 2 and 4)."""
        cfg = self.cfg
        wx, wy = waypoint
        if self.mode == WAIT:
            if ans is not None and not ans.blocked and self._aside:
                # the way opened from the refuge: back to the waypoint by the whole map's route (a straight
                # drive from a side corridor meets the wall between)
                self._aside = False
                self.global_plans += 1
                self._enter(GLOBAL, now_us + 1)
                return float(wx), float(wy), 0
            if ans is not None and not ans.blocked:
                self._enter(LOCAL, now_us)  # the way opened (a mover stepped aside)
                self.detouring = ans.detouring
                return ans.target[0], ans.target[1], 100
            if now_us - self._mode_since_us >= cfg.wait_us * min(self._all_rounds + 1, cfg.max_rounds):
                memory.pin(now_us)
                self.global_plans += 1
                self._enter(GLOBAL, now_us + 1)  # the next tick asks over the whole map
            return float(wx), float(wy), 0
        if ans is None:  # GLOBAL, no answer yet: stand still while the whole map is searched
            if now_us - self._mode_since_us > PLAN_STOP_US:
                self.stale_ticks += 1
            return float(wx), float(wy), 0
        if ans.no_route:
            self._all_rounds += 1
            # a moving scene: new points came near while the robot waited, and without what moved the
            # way would be open (a mover walking past the robot while a box closes the door: still)
            moving = memory.added - self._added_at_wait > cfg.moving_points and not ans.still_closed
            if not moving and not self._came_up:
                self._rounds += 1  # a still scene: what closes the way stays
            if self._rounds >= cfg.max_rounds or self._all_rounds >= 3 * cfg.max_rounds:
                self._enter(NO_ROUTE, now_us)
                self.no_route = f"no route to ({wx},{wy})"  # <= 50 characters with the item
            elif ans.refuge is not None and self._came_up:
                self._refuge = ans.refuge
                self._generation += 1  # the refuge's questions are not the waypoint's
                # what stands at the robot walks: seen again or forgotten, not kept a minute (a box
                # farther off stays pinned: the blocked bench's robot went round and round once it did not)
                memory.unpin_near(x, y, REFUGE_MM)
                self._enter(GIVE_WAY, now_us)
            else:
                self._enter(BACKUP, now_us)
            return float(wx), float(wy), 0
        self.detouring = ans.detouring
        if ans.held:  # the route closed ahead: stand while the planner holds to it (LocalPlanner._plan)
            return float(wx), float(wy), 0
        if self._round_taken != self.global_plans:  # the first route of this round of recoveries
            self._round_taken = self.global_plans
            self.routes_taken += 1
        elif ans.route_mm > self._followed_mm + ROUTE_SWITCH_MM:
            self.routes_taken += 1  # the route closed and the search found another way round
        self.route_mm = self._followed_mm = ans.route_mm
        return ans.target[0], ans.target[1], self._speed(now_us - ans.asked_us)

    def _giving_way(self, now_us: int, x: float, y: float, waypoint: tuple[int, int],
                    memory: ObstacleMemory) -> tuple[float, float, int]:
        """GIVE_WAY (the class docstring's step 3): to the refuge, then WAIT there."""
        wx, wy = waypoint
        gen, snap, refuge = self._generation, memory.snapshot(), self._refuge
        self.work.post(self, lambda: self._solve_refuge(gen, now_us, x, y, refuge, snap))
        ans = self._refuge_answer
        if ans is not None and (ans.generation != gen or ans.asked_us < self._mode_since_us):
            ans = None
        there = math.hypot(refuge[0] - x, refuge[1] - y) <= REFUGE_REACHED_MM
        if there or now_us - self._mode_since_us > GIVE_WAY_US:
            self.give_ways += 1
            self._aside = True
            self._generation += 1  # the waypoint's questions again, from here
            self._enter(WAIT, now_us)
            # a round spent standing aside for a mover is not a still scene's (the refuge may not see
            # the way it closed)
            self._begin_round(now_us, memory, True)
            return float(wx), float(wy), 0
        if ans is None:
            return float(wx), float(wy), 0  # the first answer comes next tick
        self.detouring = True
        return ans.target[0], ans.target[1], self._speed(now_us - ans.asked_us)

    def _solve_refuge(self, generation: int, asked_us: int, x: float, y: float, refuge: tuple[int, int],
                      memory: ObstacleMemory) -> None:
        """The worker's part while giving way: the way from the pose asked about to the refuge."""
        p = self.planner
        if generation != self._worker_generation:
            p.reset()
            self._worker_generation = generation
        target = p.target(x, y, refuge, memory, True, asked_us)
        self._refuge_answer = RefugeAnswer(generation, asked_us, target)

    def _look(self, generation: int, x: float, y: float, waypoint: tuple[int, int]) -> None:
        """The worker's part for a far waypoint: whether the map lets the robot see it."""
        self._far_sight = (generation, waypoint, self.planner.map_sight(x, y, *waypoint))

    def _solve(self, generation: int, asked_us: int, x: float, y: float, waypoint: tuple[int, int],
               memory: ObstacleMemory, whole_map: bool = False, round_since_us: int = 0) -> None:
        """The worker's part: `LocalPlanner.target` for the pose asked about (with no route: where to
        stand aside, and whether what stood still through the round's wait closes the way)."""
        if generation != self._worker_generation:
            self.planner.reset()
            self._worker_generation = generation
        p = self.planner
        tx, ty = p.target(x, y, waypoint, memory, whole_map, asked_us)
        # no route: where the robot might stand aside, should something have come up to it (GIVE_WAY)
        refuge = p.refuge(x, y, memory) if p.no_route else None
        still_closed = p.no_route and self._closed_before(x, y, waypoint, memory, round_since_us, asked_us)
        self._answer = PlanAnswer(generation, waypoint, asked_us, (tx, ty), p.detouring, whole_map, p.blocked,
                                  p.no_route, p.route_mm, p.held, refuge, still_closed)

    def _closed_before(self, x: float, y: float, waypoint: tuple[int, int], memory: ObstacleMemory,
                       since_us: int, asked_us: int) -> bool:
        """The whole map has no route over what stood still since `since_us` either (the worker's,
        after a whole-map search said no route)."""
        before = memory.standing_by(since_us)
        if len(before.points) == len(memory.points):
            return True
        q = self._still_planner
        if q is None:
            q = self._still_planner = self.planner.sharing_map()
        q.reset(points=True)
        q.target(x, y, waypoint, before, True, asked_us)
        return q.no_route


FORWARD, TURN_LEFT, TURN_RIGHT, REVERSE = range(4)  # robot_spec.ACTION_NAMES order
TURN_COMMIT_MRAD = 1571  # a turn toward a target further round than this keeps its direction (MotionGuard)
DITHER_REVERSALS = 3  # turn reversals in a row after which the guard steps forward if the front is open
ESCAPE_STEPS = 5  # steps ahead (100 mm) after turning away from a body at the flank (MotionGuard._escape)
ESCAPE_US = 3_000_000  # at most this long turning away from it
HELD_TURN_US = 500_000  # a forward step the collision monitor holds this long is turned (MotionGuard)
_FRONT = (robot_spec.SENSOR_COUNT - 1, 0, 1)  # -45, 0, +45 deg
_REAR, _REAR_SIDES, _SIDES = 4, (3, 5), (2, 6)
_LEFT_HALF, _RIGHT_HALF = (1, 2), (6, 7)  # the diagonals and sides ahead of the axle


class MotionGuard:
    """The last word on the learnt table's action (see the module docstring); one per drive."""

    def __init__(self, cfg: LocalPlannerConfig) -> None:
        self.cfg = cfg
        self.vetoes = 0  # forward steps replaced by a turn (telemetry / benchmarks)
        self.backoffs = 0  # back-offs started
        self.reset()

    def reset(self) -> None:
        self._anchor: tuple[float, float] | None = None
        self._anchor_us = 0
        self._backing_until_us = -1
        self._last = FORWARD  # the action taken on the last tick
        self._reversals = 0  # ticks in a row the turn reversed
        self._side_ref: list[float] | None = None  # the side readings when the current back-off began
        self._escape_turn: int | None = None  # turning away from a body at the flank (_escape)
        self._escape_until_us = 0
        self._escape_steps = 0  # steps ahead still to take after the escape turn

    def action(self, now_us: int, x: float, y: float, action: int, bearing_mrad: int,
               ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
               memory: ObstacleMemory, detouring: bool = False, held_us: int = 0) -> int:
        """The action to take (`detouring`: the planner steers to a sub-goal, not the waypoint: a
        robot stuck on its way there backs off wherever it stands; the table turned in place for
        seconds by a wall it had to pass close to). `held_us`: how long the collision monitor
        (control/collision.py) has held the straight part: a forward step it holds HELD_TURN_US is
        turned toward the target instead, as a veto (the table asked for it for 20 s against a
        remembered point in the path, and the robot stood)."""
        action = self._act(now_us, x, y, action, bearing_mrad, ranges_mm, status, memory, detouring, held_us)
        self._note_reverse(action == REVERSE, ranges_mm, status)
        return action

    def _act(self, now_us: int, x: float, y: float, action: int, bearing_mrad: int,
             ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
             memory: ObstacleMemory, detouring: bool, held_us: int) -> int:
        """`action` without keeping the back-off's side readings (`step` keeps them for its own)."""
        action = self._decide(now_us, x, y, action, bearing_mrad, ranges_mm, status, memory, detouring, held_us)
        turns = (TURN_LEFT, TURN_RIGHT)
        if action in turns and self._last in turns and action != self._last:
            self._reversals += 1
            if abs(bearing_mrad) > TURN_COMMIT_MRAD:
                action = self._last  # the target is behind: finish the turn begun (module docstring)
            elif self._reversals >= DITHER_REVERSALS and all(
                    collision.reading_mm(ranges_mm, status, i) >= 2 * self.cfg.veto_mm for i in _FRONT):
                # left, right, left on the spot: a step ahead breaks it (or, a body at the flank in
                # the way of that step, turning away from it)
                action, self._reversals = self._escape(now_us, x, y, FORWARD, ranges_mm, status, memory), 0
        elif action != self._last:
            self._reversals = 0
        self._last = action
        return action

    def _note_reverse(self, backing: bool, ranges_mm: list[int] | tuple[int, ...],
                      status: list[int] | tuple[int, ...]) -> None:
        """Keep the side readings of a back-off's first tick (`may_reverse` compares with them) while
        a back-off goes on or is asked for (a recovery's, refused, stays refused to its end)."""
        if not backing:
            self._side_ref = None
        elif self._side_ref is None:
            self._side_ref = [collision.reading_mm(ranges_mm, status, i) for i in _SIDES]

    def _decide(self, now_us: int, x: float, y: float, action: int, bearing_mrad: int,
                ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
                memory: ObstacleMemory, detouring: bool, held_us: int = 0) -> int:
        cfg = self.cfg
        if self._anchor is None or math.hypot(x - self._anchor[0], y - self._anchor[1]) > cfg.stuck_mm:
            self._anchor, self._anchor_us = (x, y), now_us
        if now_us < self._backing_until_us:
            if self.may_reverse(ranges_mm, status):
                return REVERSE
            self._backing_until_us = -1  # something came up behind: no more backing (checked every tick)
        if (now_us - self._anchor_us >= cfg.stuck_us and self.may_reverse(ranges_mm, status)
                and (detouring or memory.within(x, y, robot_spec.ROBOT_RADIUS_MM + cfg.backoff_near_mm))):
            self.backoffs += 1
            self._backing_until_us = now_us + cfg.backoff_us
            self._anchor, self._anchor_us = (x, y), now_us + cfg.backoff_us
            return REVERSE
        toward = TURN_LEFT if bearing_mrad >= 0 else TURN_RIGHT
        if action in (FORWARD, REVERSE) and held_us >= HELD_TURN_US:
            # (the table's own reverse too: held against a mover at the rear flank, it was asked for
            # as long as nothing changed, and nothing did)
            self.vetoes += 1
            return toward
        action = self._escape(now_us, x, y, action, ranges_mm, status, memory)
        if action == FORWARD and any(collision.reading_mm(ranges_mm, status, i) < cfg.veto_mm for i in _FRONT):
            self.vetoes += 1
            self._escape_steps = 0
            return toward
        return action

    def _escape(self, now_us: int, x: float, y: float, action: int, ranges_mm: list[int] | tuple[int, ...],
                status: list[int] | tuple[int, ...], memory: ObstacleMemory) -> int:
        """Away from a body touching the flank or a front diagonal ahead of the axle (a mover that
        walked up to the robot and stands while it would overlap it): a step ahead rubs into it, and
        the table's turn back toward the target (or the front veto's, toward a target on that side)
        undoes a single turn away. So: turn away, the same way, until a step ahead is clear
        (collision.travel_gap_mm, which counts the rim beside a near reading), then ESCAPE_STEPS
        steps ahead; at most ESCAPE_US of turning at a time. Only for a body the map does not
        explain (one the obstacle memory holds that near): a block's corner beside the robot is the
        collision monitor's, which knows the map's corners."""
        flank = [robot_spec.RANGE_TOO_FAR if i == 0 else st for i, st in enumerate(status)]  # ahead: the veto's
        # (no flank reading under CONTACT_MM: nothing there comes within veto_mm of a step ahead, and
        # the tick is spared the geometry)
        blocked = (collision.touching(ranges_mm, flank)
                   and collision.travel_gap_mm(ranges_mm, flank, False) < self.cfg.veto_mm
                   and memory.within(x, y, robot_spec.ROBOT_RADIUS_MM + collision.CONTACT_MM))
        if self._escape_turn is not None:
            if blocked and now_us < self._escape_until_us:
                self.vetoes += 1
                return self._escape_turn
            self._escape_turn, self._escape_steps = None, 0 if blocked else ESCAPE_STEPS
        if self._escape_steps > 0:
            self._escape_steps -= 1
            if not blocked:
                return FORWARD
            self._escape_steps = 0
        if action == FORWARD and blocked:
            self.vetoes += 1
            left = min(collision.reading_mm(ranges_mm, status, i) for i in _LEFT_HALF)
            right = min(collision.reading_mm(ranges_mm, status, i) for i in _RIGHT_HALF)
            self._escape_turn = TURN_RIGHT if left < right else TURN_LEFT
            self._escape_until_us = now_us + ESCAPE_US
            return self._escape_turn
        return action

    def step(self, now_us: int, x: float, y: float, action: int, bearing_mrad: int,
             ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
             memory: ObstacleMemory, planner: PlannedTarget, speed: int, held_us: int = 0) -> tuple[int, int]:
        """(action, speed %) after the guard and the planner's recoveries, as the robot's sector kind
        and the twin's bench both take them: a planned stand-still is not 'stuck', and a recovery's
        back-off reverses at full speed while the rear is clear. `held_us`: as `action`."""
        if speed == 0:
            self.still(now_us)
        action = self._act(now_us, x, y, action, bearing_mrad, ranges_mm, status, memory, planner.detouring,
                           held_us)
        if planner.reverse and self.may_reverse(ranges_mm, status):
            action, speed = REVERSE, 100
        self._note_reverse(action == REVERSE or planner.reverse, ranges_mm, status)
        return action, speed

    def still(self, now_us: int) -> None:
        """The planner holds the robot still on purpose (a recovery's wait): not stuck."""
        if self._anchor is not None:
            self._anchor_us = now_us

    def rear_clear(self, ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...]) -> bool:
        cfg = self.cfg
        return (collision.reading_mm(ranges_mm, status, _REAR) > cfg.rear_clear_mm
                and all(collision.reading_mm(ranges_mm, status, i) > cfg.rear_side_clear_mm for i in _REAR_SIDES))

    def may_reverse(self, ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...]) -> bool:
        """The rear is clear, and no side reading has fallen to veto_mm or under since the back-off
        began: a small disc between the side and rear-diagonal cones came into the side sensor's view
        only as the robot backed onto it (a back-off collision in the twin). A wall alongside, read
        as near all the way, does not stop it."""
        if not self.rear_clear(ranges_mm, status):
            return False
        ref = self._side_ref
        if ref is None:
            return True
        now = [collision.reading_mm(ranges_mm, status, i) for i in _SIDES]
        return all(d > self.cfg.veto_mm or d >= r for d, r in zip(now, ref, strict=True))
