"""The collision monitor: the last word on every wheel command (issue 32).

As nav2's collision monitor sits under any controller, this sits under every
policy kind, the exploration wander and Manual driving: the controller hands
it the command it is about to send, on the control schedule, and it keeps
the turn but limits the straight part when a range reading lies in the path:

* `path_gap_mm` is how far the round robot can drive along the arc the
  command describes (nav2's "approach" model) before its rim touches a
  point: each sensor's reading taken on its cone's centre and edge rays (the
  sim's fan, `robot_spec`), the obstacle points the policy kind remembers
  (`KindDriver.remembered_obstacles`: a disc that slipped into the 30-degree
  gap between two cones as the robot passed it), and the corners of the
  robot's map's blocks near the pose (`MapCorners`: a sensor sees a wall's
  face but can miss a corner between two cones). A wall beside a straight
  corridor is not in the way; a wall ahead, a disc on the diagonal close in,
  a corner the robot is curving into, are. Fresh-clone runs of the demo with
  obstacles ended at the bumper on a disc in such a gap, and later on a
  block's corner while arcing round it, before each was counted.
* `limit` scales the straight part by `slow_pct` when the gap is under
  `slow_mm` and removes it under `stop_mm`; turning in place is left alone
  (a round robot turning touches nothing). The bumper and stale sensors are
  the controller's own stops (FAULT/Hold); this acts before contact.

Pure integer/float stdlib; parameters CM_STOP_MM, CM_SLOW_MM, CM_SLOW_PCT
(firmware_py.mavlink.params; 0 mm switches a zone off).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from firmware_py import robot_spec
from firmware_py.mapdata import OccupancyGrid

FAR_MM = 1 << 20  # nothing in the way
_HALF_FOV = robot_spec.SENSOR_FOV_MRAD / 2000.0
_RAYS = [[a / 1000.0 + d for d in (-_HALF_FOV, 0.0, _HALF_FOV)] for a in robot_spec.SENSOR_ANGLES_MRAD]
_R = float(robot_spec.ROBOT_RADIUS_MM)
_MOUNT = float(robot_spec.SENSOR_MOUNT_RADIUS_MM)
_BASE = float(robot_spec.WHEEL_BASE_MM)
_STRAIGHT_MM = 1e6  # a turning radius beyond this is driving straight
_TWO_PI = 2.0 * math.pi


def _reading_points(ranges_mm: Sequence[int], status: Sequence[int]) -> list[tuple[float, float]]:
    """Each sensor's reading as points (mm ahead, mm left) on its cone's centre and edge rays."""
    out: list[tuple[float, float]] = []
    for i, rays in enumerate(_RAYS):
        if status[i] == robot_spec.RANGE_TOO_CLOSE:
            r = float(robot_spec.RANGE_MIN_MM)
        elif status[i] == robot_spec.RANGE_VALID:
            r = float(ranges_mm[i])
        else:
            continue
        out.extend(((_MOUNT + r) * math.cos(a), (_MOUNT + r) * math.sin(a)) for a in rays)
    return out


def travel_gap_mm(ranges_mm: Sequence[int], status: Sequence[int], reverse: bool) -> int:
    """How far (mm) the robot can drive straight ahead (`reverse`: back) before touching a read point."""
    s = -1 if reverse else 1
    return path_gap_mm(_reading_points(ranges_mm, status), s, s)


def path_gap_mm(points: Sequence[tuple[float, float]], left: int, right: int,
                reach_mm: float = 1000.0) -> int:
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
    r_turn = _BASE * abs(v2) / (2.0 * w) if w else math.inf  # signed turning radius, + to the left
    side_sign = 1.0 if r_turn >= 0 else -1.0  # mirror left/right so the turn is to the left
    rc = abs(r_turn)
    lim = _R + reach_mm
    gap = float(FAR_MM)
    for px, py in points:
        px *= fwd
        py *= side_sign
        if abs(px) > lim or abs(py) > lim:
            continue
        if rc > _STRAIGHT_MM:
            if px <= 0.0 or abs(py) >= _R:
                continue
            gap = min(gap, max(0.0, px - math.sqrt(_R * _R - py * py)))
            continue
        # centre of the turn at (0, rc); the robot's centre after turning theta is rc*(sin, -cos) from it
        qx, qy = px, py - rc
        q = math.hypot(qx, qy)
        if q == 0.0:
            continue
        k = (rc * rc + q * q - _R * _R) / (2.0 * rc * q)  # touching while sin(theta - phi) > k
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
    corner between two cones; the robot knows where the map's corners are (the demo with obstacles
    once ended at the bumper on one, arcing round a block)."""

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
        out: list[tuple[int, int]] = []
        for i in range((x_mm - within_mm) // c, (x_mm + within_mm) // c + 2):
            for j in range((y_mm - within_mm) // c, (y_mm + within_mm) // c + 2):
                for px, py in self.buckets.get((i, j), ()):
                    if abs(px - x_mm) <= within_mm and abs(py - y_mm) <= within_mm:
                        out.append((px, py))
        return out


def limit(left: int, right: int, ranges_mm: Sequence[int], status: Sequence[int], stop_mm: int, slow_mm: int,
          slow_pct: int, remembered: Sequence[tuple[float, float]] = ()) -> tuple[int, int, str]:
    """(left, right) with the straight part limited, and "", "slow" or "stop" (what it did).
    `remembered`: obstacle points the policy kind remembers, in the robot's frame (`robot_frame`):
    a disc that slipped into the gap between two sensors' cones still counts."""
    v2, w2 = left + right, right - left  # twice the straight and the turning part
    if v2 == 0 or (stop_mm <= 0 and slow_mm <= 0):
        return left, right, ""
    points = _reading_points(ranges_mm, status)
    points.extend(remembered)
    gap = path_gap_mm(points, left, right)
    if gap < stop_mm:
        v2, what = 0, "stop"
    elif gap < slow_mm:
        v2, what = v2 * slow_pct // 100, "slow"
    else:
        return left, right, ""
    # back to wheels: left = (v2 - w2) / 2, right = (v2 + w2) / 2, rounded toward zero alike
    return int((v2 - w2) / 2), int((v2 + w2) / 2), what
