"""The collision monitor: the last word on every wheel command.

As nav2's collision monitor sits under any controller, this sits under every
policy kind, the exploration wander and Manual driving: the controller hands
it the command it is about to send, on the control schedule, and it keeps
the turn but limits the straight part when a range reading lies in the path:

* `path_gap_mm`: how far the round robot can drive along the command's arc
  before its rim touches a point: the readings on each cone's centre and
  edge rays, the obstacle points the kind remembers, the corners of the
  map's blocks near the pose (`MapCorners`), and the rim across a blind gap
  beside a cone reading under `CONTACT_MM` (`_reading_points`);
* `limit` scales the straight part by `slow_pct` under `slow_mm` and removes
  it under `stop_mm`; turning in place is left alone. The bumper and stale
  sensors are the controller's own stops (FAULT/Hold); this acts before contact.

Why each kind of point counts (discs in the gap between two cones, block
corners, movers at the flank) and the measured effect: docs/architecture.md,
"Collision monitor". Pure integer/float stdlib; parameters CM_STOP_MM,
CM_SLOW_MM, CM_SLOW_PCT (firmware_py.mavlink.params; 0 mm switches a zone off).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from firmware_py import robot_spec
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.layout import Layout
from firmware_py.mapdata import MAP_MARGIN_MM, OccupancyGrid, unmapped_readings

FAR_MM = 1 << 20  # nothing in the way
_STRAIGHT_MM = 1e6  # a turning radius beyond this is driving straight
_TWO_PI = 2.0 * math.pi
# A body touching the rim in the blind gap between two cones (up to half the 45-degree spacing from a
# sensor's axis) is read by that sensor, along its cone's nearer edge, at 40 mm or less for any disc of
# radius 100 mm or more (27 for a 150-mm mover touching 22.5 degrees off): a reading under CONTACT_MM
# may be such a body, so the rim across the gaps beside that cone counts as touched.
CONTACT_MM = 45.0
_GAP_OFFSETS = tuple(math.radians(o) for o in (11.25, 15.0, 18.75, 22.5))  # the cone's edge to mid-gap


class Fan:
    """The monitor's geometry of one layout (firmware_py.layout.Layout): each sensor's centre and cone-edge
    rays, the body's radius and wheel base, and per sensor the rim points in the blind gaps beside its
    cone. Neighbours are by angle (the layout may list its sensors in any order)."""

    def __init__(self, layout: Layout = DEFAULT_LAYOUT) -> None:
        self.layout = layout
        half_fov = layout.fov_mrad / 2000.0
        angles = layout.angles_mrad
        self.rays = [[a / 1000.0 + d for d in (-half_fov, 0.0, half_fov)] for a in angles]
        self.r = float(layout.robot_radius_mm)
        self.mount = float(layout.mount_mm)
        self.base = float(layout.wheel_base_mm)
        self.range_min = float(layout.range_min_mm)
        n = len(angles)
        ccw = sorted(range(n), key=lambda i: (angles[i] % 6283, i))  # sensors round the body, CCW
        nxt = {ccw[k]: ccw[(k + 1) % n] for k in range(n)}
        prv = {ccw[k]: ccw[(k - 1) % n] for k in range(n)}
        r = self.r
        # per sensor: (the neighbour a gap leads to, the neighbour on the other side, rim points in that gap)
        self.gap_rim = [[((nxt if s == 1 else prv)[i], (prv if s == 1 else nxt)[i],
                          [(r * math.cos(a / 1000.0 + s * d), r * math.sin(a / 1000.0 + s * d)) for d in _GAP_OFFSETS])
                         for s in (1, -1)]
                        for i, a in enumerate(angles)]


DEFAULT_FAN = Fan()


def touching(ranges_mm: Sequence[int], status: Sequence[int], fan: Fan = DEFAULT_FAN) -> bool:
    """A reading under CONTACT_MM (callers then work out which readings their map explains)."""
    return any(reading_mm(ranges_mm, status, i) < CONTACT_MM for i in range(len(fan.rays)))


def _reading_points(ranges_mm: Sequence[int], status: Sequence[int],
                    mapped: Sequence[bool] = (), fan: Fan = DEFAULT_FAN) -> list[tuple[float, float]]:
    """Each sensor's reading as points (mm ahead, mm left) on its cone's centre and edge rays; a
    reading under CONTACT_MM adds points on the rim across the blind gaps beside its cone, except a
    gap whose far neighbour reads CONTACT_MM or more while the neighbour on the other side also reads
    under it (the body is in that other gap: a mover touching the flank behind the axle is read by
    the side and rear-diagonal sensors, and does not stop a step ahead, away from it), and except
    for a reading the robot's map explains (`mapped[i]`: a wall or block whose corners the monitor
    is given as points; a block's corner beside the robot held every step past it)."""
    out: list[tuple[float, float]] = []
    near = [reading_mm(ranges_mm, status, i) for i in range(len(fan.rays))]
    mount = fan.mount
    for i, rays in enumerate(fan.rays):
        r = near[i]
        if r == math.inf:
            continue
        if mapped and mapped[i]:
            r = max(r, fan.range_min)  # a wall's face: its corners are points already
        out.extend(((mount + r) * math.cos(a), (mount + r) * math.sin(a)) for a in rays)
        if r < CONTACT_MM and not (mapped and mapped[i]):
            for toward, other, rim in fan.gap_rim[i]:
                if not (near[other] < CONTACT_MM <= near[toward]):
                    out.extend(rim)
    return out


def reading_mm(ranges_mm: Sequence[int], status: Sequence[int], i: int) -> float:
    """Sensor i's reading as a distance: too close is 0 (somewhere under the minimum), nothing or
    invalid is infinite (the motion guard compares readings with these too)."""
    if status[i] == robot_spec.RANGE_TOO_CLOSE:
        return 0.0  # somewhere under the sensor's minimum: take the worst
    if status[i] == robot_spec.RANGE_VALID:
        return float(ranges_mm[i])
    return math.inf


def travel_gap_mm(ranges_mm: Sequence[int], status: Sequence[int], reverse: bool,
                  mapped: Sequence[bool] = (), fan: Fan = DEFAULT_FAN) -> int:
    """How far (mm) the robot can drive straight ahead (`reverse`: back) before touching a read point
    (`mapped`: as `limit`'s)."""
    s = -1 if reverse else 1
    return path_gap_mm(_reading_points(ranges_mm, status, mapped, fan), s, s, fan=fan)


def path_gap_mm(points: Sequence[tuple[float, float]], left: int, right: int,
                reach_mm: float = 1000.0, fan: Fan = DEFAULT_FAN) -> int:
    """How far (mm, along its path) the round robot driving the wheel speeds `left`, `right` goes
    before its rim touches one of `points` (robot frame: mm ahead, mm left); FAR_MM when none
    within `reach_mm` of travel. The path is the command's arc (nav2's "approach" model: a corner
    the robot is turning into is in the way though it is beside the straight corridor); points the
    robot touches now and moves away from do not count."""
    v2, w2 = left + right, right - left
    if v2 == 0:
        return FAR_MM
    fwd = 1.0 if v2 > 0 else -1.0
    # mirror into the frame where the robot drives forward: backing reverses "ahead" and the turn sense
    w = w2 * fwd
    rr = fan.r
    r_turn = fan.base * abs(v2) / (2.0 * w) if w else math.inf  # signed turning radius, + to the left
    side_sign = 1.0 if r_turn >= 0 else -1.0  # mirror left/right so the turn is to the left
    rc = abs(r_turn)
    lim = rr + reach_mm
    gap = float(FAR_MM)
    for px, py in points:
        px *= fwd
        py *= side_sign
        if abs(px) > lim or abs(py) > lim:
            continue
        if rc > _STRAIGHT_MM:
            if px <= 0.0 or abs(py) >= rr:
                continue
            gap = min(gap, max(0.0, px - math.sqrt(rr * rr - py * py)))
            continue
        # centre of the turn at (0, rc); the robot's centre after turning theta is rc*(sin, -cos) from it
        qx, qy = px, py - rc
        q = math.hypot(qx, qy)
        if q == 0.0:
            continue
        k = (rc * rc + q * q - rr * rr) / (2.0 * rc * q)  # touching while sin(theta - phi) > k
        if k >= 1.0:
            continue
        phi = math.atan2(qy, qx)
        a = math.asin(max(-1.0, k))
        lo, hi = a + phi, math.pi - a + phi  # the window of theta (mod 2 pi) in contact
        shift = math.floor(hi / _TWO_PI) * _TWO_PI  # the window whose end is in [0, 2 pi)
        lo, hi = lo - shift, hi - shift
        if lo <= 0.0:  # touching now: in the way only if the turn brings the centre nearer
            if math.cos(phi) > 0.0:
                gap = 0.0
            continue
        if lo <= math.pi:
            gap = min(gap, rc * lo)
    return max(0, int(gap))


def robot_frame(points: Sequence[tuple[int, int]], pose_mm: tuple[int, int, int],
                within_mm: float = 1000.0) -> list[tuple[float, float]]:
    """World points (mm) near the pose, as (ahead, left) in the robot's frame."""
    x, y, heading = pose_mm
    c, s = math.cos(heading / 1000.0), math.sin(heading / 1000.0)
    out = []
    for px, py in points:
        dx, dy = px - x, py - y
        if abs(dx) <= within_mm and abs(dy) <= within_mm:
            out.append((dx * c + dy * s, -dx * s + dy * c))
    return out


class MapCorners:
    """The corners of a map's occupied cells that stick out into free space (world mm), bucketed by
    cell for a quick look round the pose. Range sensors see a wall's face but can miss a block's
    corner between two cones; the robot knows where the map's corners are."""

    def __init__(self, grid: OccupancyGrid) -> None:
        self.grid = grid
        self.cell_mm = c = grid.cell_mm
        self.buckets: dict[tuple[int, int], list[tuple[int, int]]] = {}
        for i in range(grid.width + 1):
            for j in range(grid.height + 1):  # vertex (i, j): x = i * c east, y = j * c north
                sw, se = grid.occupied(i - 1, grid.height - j), grid.occupied(i, grid.height - j)
                nw, ne = grid.occupied(i - 1, grid.height - 1 - j), grid.occupied(i, grid.height - 1 - j)
                if sw + se + nw + ne == 1 or (sw == ne and se == nw and sw != se):
                    self.buckets.setdefault((i, j), []).append((i * c, j * c))

    def near(self, x_mm: int, y_mm: int, within_mm: int) -> list[tuple[int, int]]:
        """The corners within `within_mm` (a square) of a world point."""
        c = self.cell_mm
        return [(px, py) for i in range((x_mm - within_mm) // c, (x_mm + within_mm) // c + 2)
                for j in range((y_mm - within_mm) // c, (y_mm + within_mm) // c + 2)
                for px, py in self.buckets.get((i, j), ())
                if abs(px - x_mm) <= within_mm and abs(py - y_mm) <= within_mm]


def limit(left: int, right: int, ranges_mm: Sequence[int], status: Sequence[int], stop_mm: int, slow_mm: int,
          slow_pct: int, remembered: Sequence[tuple[float, float]] = (),
          mapped: Sequence[bool] = (), fan: Fan = DEFAULT_FAN) -> tuple[int, int, str]:
    """(left, right) with the straight part limited, and "", "slow" or "stop" (what it did).
    `remembered`: obstacle points the policy kind remembers, in the robot's frame (`robot_frame`):
    a disc that slipped into the gap between two sensors' cones still counts. `mapped`: per sensor,
    whether the robot's map explains its reading (`mapped_readings`; empty: none does)."""
    v2, w2 = left + right, right - left  # twice the straight and the turning part
    if v2 == 0 or (stop_mm <= 0 and slow_mm <= 0):
        return left, right, ""
    points = _reading_points(ranges_mm, status, mapped, fan)
    points.extend(remembered)
    gap = path_gap_mm(points, left, right, fan=fan)
    if gap < stop_mm:
        v2, what = 0, "stop"
    elif gap < slow_mm:
        v2, what = v2 * slow_pct // 100, "slow"
    else:
        return left, right, ""
    # back to wheels: left = (v2 - w2) / 2, right = (v2 + w2) / 2, rounded toward zero alike
    return int((v2 - w2) / 2), int((v2 + w2) / 2), what


def mapped_readings(grid: OccupancyGrid, pose_mm: tuple[int, int, int], ranges_mm: list[int] | tuple[int, ...],
                    status: list[int] | tuple[int, ...], margin_mm: int = MAP_MARGIN_MM,
                    fan: Fan = DEFAULT_FAN) -> list[bool]:
    """Per sensor: the map explains its reading at this pose (`unmapped_ends`); a too-far or
    invalid reading is not a reading (False). The collision monitor's `mapped`, which it reads only
    for a reading under CONTACT_MM: with none, [] (the map is not asked; the controller's tick and
    the twin's hot loop are spared it)."""
    if not touching(ranges_mm, status, fan):
        return []
    x, y, heading = pose_mm
    layout = None if fan is DEFAULT_FAN else fan.layout
    unmapped = unmapped_readings(grid, x, y, heading, ranges_mm, status, margin_mm, layout)
    return [u < 0 and status[i] in (robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_CLOSE)
            for i, u in enumerate(unmapped)]


class CollisionMonitor:
    """The collision monitor as a part of the controller, downstream of whatever made the command (a
    policy kind, the wander, Manual): the command in, the command out (`limit_command`). Its inputs:
    the command, the readings, the pose the robot drives by, the obstacle points the kind remembers,
    the map, the monitor's zones. What it tells back is how long it has held the straight part
    (`held_us`: the kind's `DriveTick.blocked_us`) and what it counted (`ticks`)."""

    def __init__(self, layout: Layout = DEFAULT_LAYOUT) -> None:
        self.fan = DEFAULT_FAN if layout == DEFAULT_LAYOUT else Fan(layout)  # where the sensors look
        self.ticks = {"slow": 0, "stop": 0}  # commands it limited
        self.stop_since_us: int | None = None  # it has removed the straight part since
        self._corners: MapCorners | None = None  # the block corners of the map it was last given

    def held_us(self, now_us: int) -> int:
        """How long the straight part has been held at zero, up to the last command (0: it is not)."""
        return 0 if self.stop_since_us is None else now_us - self.stop_since_us

    def forget_map(self) -> None:
        self._corners = None

    def _corners_near(self, grid: OccupancyGrid | None, pose: tuple[int, int, int],
                      within_mm: int) -> list[tuple[int, int]]:
        """The map's block corners within reach of the monitor (none without a map)."""
        if grid is None:
            return []
        corners = self._corners
        if corners is None or corners.grid is not grid:
            self._corners = corners = MapCorners(grid)
        return corners.near(pose[0], pose[1], within_mm)

    def limit_command(self, now_us: int, left: int, right: int, ranges_mm: list[int] | tuple[int, ...],
                      status: list[int] | tuple[int, ...],
                      pose: tuple[int, int, int], remembered: Sequence[tuple[int, int]], grid: OccupancyGrid | None,
                      stop_mm: int, slow_mm: int, slow_pct: int) -> tuple[int, int]:
        """The command as it may be sent (module docstring; `remembered`: world points). The caller
        sets `stop_since_us` to None for a zero command (nothing to hold)."""
        fan = self.fan
        seen = list(remembered) + self._corners_near(grid, pose, slow_mm + 2 * fan.layout.robot_radius_mm)
        near = robot_frame(seen, pose) if seen else []
        mapped = mapped_readings(grid, pose, ranges_mm, status, fan=fan) if grid is not None else []
        left, right, limited = limit(left, right, ranges_mm, status, stop_mm, slow_mm, slow_pct, near, mapped, fan)
        if limited:
            self.ticks[limited] += 1
        if limited != "stop":
            self.stop_since_us = None
        elif self.stop_since_us is None:
            self.stop_since_us = now_us
        return left, right

    def shut(self, left: int, right: int, ranges_mm: Sequence[int], status: Sequence[int], slow_mm: int) -> bool:
        """The way ahead counts as shut for the stall watch: the monitor holds the straight part, or
        nothing was sent with a reading in the path within `slow_mm`."""
        return self.stop_since_us is not None or (
            not (left or right) and travel_gap_mm(ranges_mm, status, False, fan=self.fan) < slow_mm)
