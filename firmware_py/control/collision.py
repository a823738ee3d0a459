"""The collision monitor: the last word on every wheel command (issue 32).

As nav2's collision monitor sits under any controller, this sits under every
policy kind, the exploration wander and Manual driving: the controller hands
it the command it is about to send, on the control schedule, and it keeps
the turn but limits the straight part when a range reading lies in the path:

* `travel_gap_mm` is how far the round robot can move straight ahead (or
  back) before it touches the nearest point a range sensor reads: each
  sensor's reading is taken on its cone's centre and edge rays (the sim's
  fan, `robot_spec`), a point beside the robot's swept corridor (farther
  than its radius to the side) is not in the way. A wall beside a corridor
  is not; a wall ahead, a disc on the diagonal close in, are. Obstacle
  points the policy kind remembers (the sector kind's unmapped-obstacle
  memory, `KindDriver.remembered_obstacles`) count the same way: a disc
  that slipped into the 30-degree gap between two sensors' cones as the
  robot passed it is still in the way (the demo with obstacles once ended
  at the bumper on one).
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

FAR_MM = 1 << 20  # nothing in the way
_HALF_FOV = robot_spec.SENSOR_FOV_MRAD / 2000.0
_RAYS = [[a / 1000.0 + d for d in (-_HALF_FOV, 0.0, _HALF_FOV)] for a in robot_spec.SENSOR_ANGLES_MRAD]
_R = float(robot_spec.ROBOT_RADIUS_MM)
_MOUNT = float(robot_spec.SENSOR_MOUNT_RADIUS_MM)


def travel_gap_mm(ranges_mm: Sequence[int], status: Sequence[int], reverse: bool) -> int:
    """How far (mm) the robot can drive straight ahead (`reverse`: back) before touching a read point."""
    gap = float(FAR_MM)
    sign = -1.0 if reverse else 1.0
    for i, rays in enumerate(_RAYS):
        if status[i] == robot_spec.RANGE_TOO_CLOSE:
            r = float(robot_spec.RANGE_MIN_MM)
        elif status[i] == robot_spec.RANGE_VALID:
            r = float(ranges_mm[i])
        else:
            continue
        for a in rays:
            ahead = sign * (_MOUNT + r) * math.cos(a)
            side = (_MOUNT + r) * math.sin(a)
            if ahead <= 0.0 or abs(side) >= _R:
                continue
            gap = min(gap, ahead - math.sqrt(_R * _R - side * side))
    return max(0, int(gap))


def points_gap_mm(points: Sequence[tuple[float, float]], reverse: bool) -> int:
    """As `travel_gap_mm` for points already in the robot's frame (mm ahead, mm to the left)."""
    gap = float(FAR_MM)
    sign = -1.0 if reverse else 1.0
    for ahead, side in points:
        ahead *= sign
        if ahead <= 0.0 or abs(side) >= _R:
            continue
        gap = min(gap, ahead - math.sqrt(_R * _R - side * side))
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


def limit(left: int, right: int, ranges_mm: Sequence[int], status: Sequence[int], stop_mm: int, slow_mm: int,
          slow_pct: int, remembered: Sequence[tuple[float, float]] = ()) -> tuple[int, int, str]:
    """(left, right) with the straight part limited, and "", "slow" or "stop" (what it did).
    `remembered`: obstacle points the policy kind remembers, in the robot's frame (`robot_frame`):
    a disc that slipped into the gap between two sensors' cones still counts."""
    v2, w2 = left + right, right - left  # twice the straight and the turning part
    if v2 == 0 or (stop_mm <= 0 and slow_mm <= 0):
        return left, right, ""
    gap = min(travel_gap_mm(ranges_mm, status, reverse=v2 < 0), points_gap_mm(remembered, reverse=v2 < 0))
    if gap < stop_mm:
        v2, what = 0, "stop"
    elif gap < slow_mm:
        v2, what = v2 * slow_pct // 100, "slow"
    else:
        return left, right, ""
    # back to wheels: left = (v2 - w2) / 2, right = (v2 + w2) / 2, rounded toward zero alike
    return int((v2 - w2) / 2), int((v2 + w2) / 2), what
