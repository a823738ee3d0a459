"""Re-planning around what the robot's range sensors find (`qnav mission upload --plan --follow`).

When an obstacle the map does not show stands across the planned waypoints, the
robot may stall (STATUSTEXT "no progress ...") while it streams its range readings
(OBSTACLE_DISTANCE, BODY_FRD) and pose; the ground station re-plans, as nav2 does:

* `UnmappedPoints` turns each OBSTACLE_DISTANCE into world points: per range
  sensor of the robot's `Layout` (its profile's), the bin on that sensor's axis
  (a bin carries the angle only to 5 deg, not which sensor), placed at the
  sensor's angle on the body's rim with the pose interpolated to the reading's
  time (poses and ranges stream at different rates). A reading counts only when
  at least `margin_mm` shorter than the same sensor would read on the known map
  (the twin's sensor model, `sense_one`), so map walls never count; nor do
  readings beyond `max_range_mm` (a cone's nearest hit lies off its axis by up
  to r sin(7.5 deg)), at the sensor's reach, or no echo. Points older than
  `window_us` of robot time are forgotten (a mover walks on).
* `raster_plan` plans on the scenario raster (`nav.obstacles`) for the body
  grown by 75 mm, shortest 8-connected path (`maps.octile_distances`, then
  steepest descent) pruned to line-of-sight segments of at most 1 m.
* `MissionFollower`, the follow loop's pure core (`follow_mission` its shell):
  on "no progress" it plans from the robot's position through the targets left
  (the robot holds on the new mission, the shell restarts Auto); it gives up
  when nothing unmapped was seen, no path is left, or after `max_replans`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from firmware_py import robot_spec
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.layout import Layout
from ground_station.maps import GridMap
from ground_station.monitor.model import obstacle_increment_deg

MARGIN_MM = 150.0  # a reading this much shorter than the map's is something the map does not show
MAX_RANGE_MM = 1000.0
WINDOW_US = 15_000_000
POINT_RADIUS_MM = 25.0  # each point as a small disc on the raster
STALL_TEXT = "no progress"  # firmware_py.control.progress.ProgressWatch's STATUSTEXT
MAX_REPLANS = 5
START_SEARCH_STEPS = 8  # raster steps searched for a free start point (the robot stalls close to the obstacle)


@functools.lru_cache(maxsize=8)
def _axis_bins(layout: Layout, increment_deg: float, angle_offset_deg: float) -> tuple[int | None, ...]:
    """Per sensor of `layout`, the OBSTACLE_DISTANCE bin holding its reading: of the bins the robot
    fills from its cone (`Telemetry.obstacle_distance`: centre within max(half the field of view,
    half a bin) of its axis), the one nearest its axis that no other sensor's cone fills, else
    the bin nearest its axis."""
    if increment_deg <= 0:
        return (None,) * layout.count
    n = max(1, round(360.0 / increment_deg))
    reach = max(math.degrees(layout.fov_mrad / 1000.0) / 2, increment_deg / 2)
    axes = [(-math.degrees(a / 1000.0)) % 360.0 for a in layout.angles_mrad]  # CCW from nose -> clockwise

    def off(k: int, frd: float) -> float:
        return abs((angle_offset_deg + k * increment_deg - frd + 180.0) % 360.0 - 180.0)

    out: list[int | None] = []
    for j, frd in enumerate(axes):
        nearest = round(((frd - angle_offset_deg) % 360.0) / increment_deg) % n
        own = [k for k in range(n) if off(k, frd) <= reach
               and not any(off(k, other) <= reach for i, other in enumerate(axes) if i != j)]
        out.append(min(own, key=lambda k: (off(k, frd), k)) if own else nearest)
    return tuple(out)


def sensor_readings(distances_cm, increment_deg: float, angle_offset_deg: float, min_cm: int,
                    max_cm: int, layout: Layout = DEFAULT_LAYOUT) -> list[int | None]:
    """Per range sensor of `layout`, in its order, the reading (mm) of an OBSTACLE_DISTANCE in
    MAV_FRAME_BODY_FRD (bins clockwise from the nose) from the bin on its axis (`_axis_bins`);
    None where it holds none (UINT16_MAX unknown, or max_cm + 1 = nothing within range)."""
    out: list[int | None] = []
    for i in _axis_bins(layout, increment_deg, angle_offset_deg):
        d = None
        if i is not None and i < len(distances_cm) and min_cm <= distances_cm[i] <= max_cm:
            d = 10 * int(distances_cm[i])
        out.append(d)
    return out


class UnmappedPoints:
    """Points the robot's range sensors saw that the known map does not explain."""

    def __init__(self, gridmap: GridMap, margin_mm: float = MARGIN_MM, max_range_mm: float = MAX_RANGE_MM,
                 window_us: int = WINDOW_US, layout: Layout = DEFAULT_LAYOUT) -> None:
        self.known = gridmap
        self.layout = layout  # the robot's sensors (readings in its order) and body
        self._tw: tuple | None = None
        self.occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
        self.cell_mm = gridmap.cell_size_m * 1000.0
        self.margin_mm = margin_mm
        self.max_range_mm = max_range_mm
        self.window_us = window_us
        self.points: list[tuple[int, float, float]] = []  # (robot time us, x, y)

    def observe(self, t_us: int, x_mm: float, y_mm: float, heading_rad: float,
                readings_mm: list[int | None]) -> int:
        """Add the unexplained readings of one scan (per sensor of the layout) taken at pose (x, y,
        heading CCW from east); returns how many."""
        from ground_station.learn.sector.twin import DEFAULT_TW, TwinRobot, sense_one

        lay = self.layout
        if self._tw is None:  # the twin of these sensors (the built-in robot's: the twin's own)
            self._tw = DEFAULT_TW if lay == DEFAULT_LAYOUT else TwinRobot(
                radius_mm=lay.robot_radius_mm, angles_mrad=lay.angles_mrad, ranges_mm=lay.max_ranges_mm).arrays()
        tw = self._tw
        h, w = self.occ.shape
        n = 0
        for i, d in enumerate(readings_mm[:lay.count]):
            if d is None or d > self.max_range_mm or d >= lay.max_ranges_mm[i]:
                continue  # nothing seen, too far to place, or at the sensor's reach (no echo)
            expected, status = sense_one(self.occ, h, w, self.cell_mm, x_mm, y_mm, heading_rad, i, tw)
            if status == robot_spec.RANGE_VALID and d > expected - self.margin_mm:
                continue  # the map's own wall
            a = heading_rad + lay.angles_mrad[i] / 1000.0
            r = lay.mount_mm + d
            self.points.append((t_us, x_mm + r * math.cos(a), y_mm + r * math.sin(a)))
            n += 1
        return n

    def recent(self, now_us: int) -> list[tuple[float, float]]:
        """The points seen within the window before `now_us` (older ones are dropped)."""
        self.points = [p for p in self.points if now_us - p[0] <= self.window_us]
        return [(x, y) for _, x, y in self.points]


def raster_plan(gridmap: GridMap, points: list[tuple[float, float]], start_mm: tuple[float, float],
                goals_mm: list[tuple[float, float]], max_segment_mm: float = 1000.0,
                radius_mm: float = robot_spec.ROBOT_RADIUS_MM) -> list[list[tuple[float, float]]]:
    """Per goal, the waypoints (mm) from the previous one (first: start_mm) round the points, on
    the scenario raster for a body of `radius_mm` grown by the margin; MapError when a leg has no path."""
    from ground_station.maps import MapError, octile_distances
    from ground_station.nav.obstacles import CSPACE_MARGIN_MM, RASTER_MM, cspace, raster_nearest

    occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
    cell = gridmap.cell_size_m * 1000.0
    body_mm = float(radius_mm) + CSPACE_MARGIN_MM  # round the unmapped points
    # round the map's walls the same, down to what a one-cell corridor leaves on the raster (its
    # middle points, half a raster step off centre): the robot's route goes through such corridors,
    # and a wider body kept 75 mm off both walls would have none left
    wall_clear = max(float(radius_mm), min(body_mm, 0.5 * cell - 0.5 * RASTER_MM))
    free = cspace(occ, cell, np.zeros((0, 3)), RASTER_MM, wall_clear)
    ny, nx = free.shape
    if points:  # cspace's disc test, at the body's full clearance
        px = (np.arange(nx) + 0.5) * RASTER_MM
        py = (np.arange(ny) + 0.5) * RASTER_MM
        for x, y in points:
            d = body_mm + POINT_RADIUS_MM
            free &= ((px[None, :] - x) ** 2 + (py[:, None] - y) ** 2) >= d * d

    def clear(a: tuple[int, int], b: tuple[int, int]) -> bool:
        n = max(abs(b[0] - a[0]), abs(b[1] - a[1])) * 2 + 1
        for k in range(n + 1):
            t = k / n
            if not free[round(a[1] + t * (b[1] - a[1])), round(a[0] + t * (b[0] - a[0]))]:
                return False
        return True

    legs = []
    here = start_mm
    for gx, gy in goals_mm:
        s, g = raster_nearest(free, *here, START_SEARCH_STEPS), raster_nearest(free, gx, gy, START_SEARCH_STEPS)
        if s is None or g is None:
            raise MapError(f"no free raster point near {'the robot' if s is None else 'the goal'}")
        dist = octile_distances(~free, *g)  # free[y, x]: rows are raster y, columns raster x
        if not math.isfinite(dist[s[1], s[0]]):
            raise MapError(f"no path from ({here[0]:.0f}, {here[1]:.0f}) to ({gx:.0f}, {gy:.0f}) mm")
        path = [s]
        while path[-1] != g:  # steepest descent of the distance field
            x, y = path[-1]
            path.append(min(((xx, yy) for yy in range(max(0, y - 1), min(ny, y + 2))
                             for xx in range(max(0, x - 1), min(nx, x + 2))), key=lambda p: dist[p[1], p[0]]))
        steps = max_segment_mm / RASTER_MM
        wps = []
        a = path[0]
        if math.hypot(here[0] - (a[0] + 0.5) * RASTER_MM, here[1] - (a[1] + 0.5) * RASTER_MM) > RASTER_MM:
            wps.append(a)  # first step out of the obstacle's margin
        i = 0
        while i < len(path) - 1:
            j = i + 1
            while j + 1 < len(path) and clear(path[i], path[j + 1]) and math.dist(path[i], path[j + 1]) <= steps:
                j += 1
            wps.append(path[j])
            i = j
        out = [((px + 0.5) * RASTER_MM, (py + 0.5) * RASTER_MM) for px, py in wps]
        out[-1] = (gx, gy)
        legs.append(out)
        here = (gx, gy)
    return legs


@dataclass
class Replan:
    """A new mission: LOCAL_NED items from the robot's position through the targets left."""

    items: list[tuple[int, int, int]]
    target_seq: list[int]
    points: int  # unmapped points planned around
    text: str


@dataclass
class Finished:
    ok: bool
    text: str


def _wrap(a: float) -> float:
    return math.remainder(a, 2.0 * math.pi)


@dataclass
class MissionFollower:
    """The follow loop's core: `handle(msg)` for the robot's FOLLOW_TYPES messages, `text(line)`
    for its STATUSTEXTs; each returns a `Replan` to upload, a `Finished`, or None."""

    gridmap: GridMap
    targets: list[tuple[int, int]]  # cells, in visiting order
    target_seq: list[int]  # the current mission's item index of each target (reached ones: -1)
    radius_mm: float = robot_spec.ROBOT_RADIUS_MM  # the robot's body (its profile's): what re-plans keep clear
    layout: Layout = DEFAULT_LAYOUT  # the robot's range sensors (its profile's): where each reading is placed
    max_replans: int = MAX_REPLANS
    reached: int = 0  # targets reached so far
    replans: int = 0
    seen: UnmappedPoints | None = None
    _pos: tuple[int, float, float] | None = None  # last LOCAL_POSITION_NED: (time ms, x east, y north) mm
    _poses: list[tuple[int, float, float, float]] = field(default_factory=list)  # (ms, x, y, heading) history
    _scans: list = field(default_factory=list)  # OBSTACLE_DISTANCE waiting for a later pose

    def __post_init__(self) -> None:
        if self.seen is None:
            self.seen = UnmappedPoints(self.gridmap, layout=self.layout)

    def _pose_at(self, t_ms: float) -> tuple[float, float, float] | None:
        """The pose at robot time t_ms, interpolated between the poses around it."""
        if self._poses and self._poses[-1][0] == t_ms:  # sent in the same telemetry tick
            return self._poses[-1][1:]
        for (t0, x0, y0, h0), (t1, x1, y1, h1) in zip(self._poses, self._poses[1:], strict=False):
            if t0 <= t_ms <= t1:
                f = 0.0 if t1 == t0 else (t_ms - t0) / (t1 - t0)
                return x0 + f * (x1 - x0), y0 + f * (y1 - y0), h0 + f * _wrap(h1 - h0)
        return None

    def handle(self, msg) -> Replan | Finished | None:  # noqa: ANN001 - a pymavlink message
        kind = msg.get_type()
        if kind == "LOCAL_POSITION_NED":
            self._pos = (msg.time_boot_ms, msg.y * 1000.0, msg.x * 1000.0)  # east, north
        elif kind == "ATTITUDE":
            if self._pos is not None and self._pos[0] == msg.time_boot_ms:  # both from one telemetry tick
                self._poses = [*self._poses[-20:], (msg.time_boot_ms, self._pos[1], self._pos[2],
                                                    math.pi / 2 - msg.yaw)]
                self._flush()
        elif kind == "OBSTACLE_DISTANCE":
            if msg.frame == 12:  # MAV_FRAME_BODY_FRD: what the robot sends
                self._scans = [*self._scans[-20:], (msg.time_usec, sensor_readings(
                    msg.distances, obstacle_increment_deg(msg), msg.angle_offset, msg.min_distance, msg.max_distance,
                    self.layout))]
                self._flush()
        elif kind == "MISSION_ITEM_REACHED":
            left = self.target_seq[self.reached:]
            if left and msg.seq == left[0]:
                self.reached += 1
                if self.reached == len(self.targets):
                    return Finished(True, f"all {len(self.targets)} targets reached "
                                          f"({self.replans} re-plan{'s' if self.replans != 1 else ''})")
        return None

    def _flush(self) -> None:
        """Place the scans the pose history now brackets; drop those it never will."""
        assert self.seen is not None
        keep = []
        for t_us, readings in self._scans:
            pose = self._pose_at(t_us / 1000.0)
            if pose is not None:
                self.seen.observe(t_us, *pose, readings)
            elif not self._poses or t_us / 1000.0 > self._poses[-1][0]:
                keep.append((t_us, readings))  # its later pose is still to come
        self._scans = keep

    def text(self, text: str) -> Replan | Finished | None:
        """A whole STATUSTEXT from the robot (the link reassembles chunked ones)."""
        return self._replan(text) if STALL_TEXT in text else None

    def _replan(self, why: str) -> Replan | Finished:
        if not self._poses:
            return Finished(False, f"robot says '{why}' but sent no pose to re-plan from")
        if self.replans >= self.max_replans:
            return Finished(False, f"robot says '{why}' after {self.replans} re-plans: giving up")
        assert self.seen is not None
        points = self.seen.recent(self._poses[-1][0] * 1000)
        if not points:
            return Finished(False, f"robot says '{why}' and its range readings show nothing the map does not: "
                                   "nothing to re-plan around")
        from firmware_py.mavlink.frames import LOCAL_ITEM_SCALE
        from ground_station.maps import MapError
        from ground_station.mavlink.link import mavlink

        left = self.targets[self.reached:]
        c = self.gridmap.cell_size_m * 1000.0
        goals = [((col + 0.5) * c, (self.gridmap.height - row - 0.5) * c) for col, row in left]
        here = self._poses[-1][1:3]
        try:
            legs = raster_plan(self.gridmap, points, here, goals, radius_mm=self.radius_mm)
        except MapError as exc:
            return Finished(False, f"no path round the {len(points)} unmapped points: {exc}")
        frame = mavlink().MAV_FRAME_LOCAL_NED
        items: list[tuple[int, int, int]] = []
        seq = []
        for leg in legs:
            items += [(frame, round(y * LOCAL_ITEM_SCALE / 1000), round(x * LOCAL_ITEM_SCALE / 1000)) for x, y in leg]
            seq.append(len(items) - 1)
        self.replans += 1
        self.target_seq = [-1] * self.reached + seq  # the new mission's items number from 0
        return Replan(items, seq, len(points), f"re-plan {self.replans}: round {len(points)} unmapped points; "
                                               f"{len(items)} waypoints to {len(left)} target(s)")


FOLLOW_TYPES = ["LOCAL_POSITION_NED", "ATTITUDE", "OBSTACLE_DISTANCE", "MISSION_ITEM_REACHED"]


def follow_mission(link, follower: MissionFollower, timeout_s: float, say) -> Finished:  # noqa: ANN001
    """Run `follower` on a `Link` until it finishes or `timeout_s` (wall) pass: each `Replan` is
    uploaded and the robot put back in Auto (a new mission holds it). `say(line)` reports."""
    import time

    from firmware_py.vehicle import Mode

    m = link.m
    seen = len(link.texts)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        msg = link.recv(FOLLOW_TYPES, timeout_s=0.2)
        outs = [follower.handle(msg)] if msg is not None else []
        while seen < len(link.texts):
            seen += 1
            outs.append(follower.text(link.texts[seen - 1]))
        for out in outs:
            if isinstance(out, Finished):
                return out
            if isinstance(out, Replan):
                say(out.text)
                link.mission_upload(out.items)
                link.command(m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(Mode.AUTO))
                seen = len(link.texts)  # texts of the old mission's stall are answered
    return Finished(False, f"timeout: {follower.reached} of {len(follower.targets)} targets reached in "
                           f"{timeout_s:g} s ({follower.replans} re-plans)")
