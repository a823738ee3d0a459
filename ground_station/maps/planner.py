"""Global guidance for the sector policy: the ground station's path planner.

A global planner on the known map and a local controller that follows it, as nav2
splits them: the robot gets a mission of intermediate waypoints and the learnt
sector policy only drives to the current one (a memoryless bearing policy cannot
leave a U-shaped pocket whose exit lies behind it). The training twin and the
evaluation use the same planner and acceptance radius (`GOAL_TOLERANCE_MM`).

Plan: descend the goal's octile distance field from the start cell to a
shortest cell path (ties -> the neighbour nearest the goal, so the path hugs
the straight line), then prune it greedily to the farthest path vertex whose
straight segment keeps the robot's disc grown by `margin_mm` clear of every
obstacle cell and the map border (exact segment-to-square distances), at most
`max_segment_mm` long. When no farther vertex is clear the next path cell is
taken: moves between neighbouring free cell centres are always clear for a
bare disc below half the cell.
Waypoints are cell centres; the last is the goal's. `radius_mm` is the
robot profile's body radius (`--profile`; the trainer plans with it too).
"""

from __future__ import annotations

import math

import numpy as np

from firmware_py import robot_spec
from ground_station.jitcache import numba
from ground_station.maps import GridMap, MapError, octile_distances
from ground_station.maps.distances import octile_moves

DEFAULT_MARGIN_MM = 75  # extra clearance of a pruned segment beyond the robot's radius
# Longest segment: the sector state knows the bearing only to within half a
# sector, so the robot may pursue its waypoint up to ~12 deg off (15 sectors)
# and drift sideways ~7 % of a segment's length; 1 m keeps that well inside
# the 100 mm a one-cell corridor leaves beside the disc. 0 = no limit.
DEFAULT_MAX_SEGMENT_MM = 1000
_TIE = 1e-3  # distance fields are float32 in the trainer: equal within this


@numba.njit(cache=True)
def _seg_point_d2(ax: float, ay: float, bx: float, by: float, px: float, py: float) -> float:
    dx = bx - ax
    dy = by - ay
    L2 = dx * dx + dy * dy
    t = 0.0
    if L2 > 0.0:
        t = ((px - ax) * dx + (py - ay) * dy) / L2
        t = min(1.0, max(0.0, t))
    qx = ax + t * dx - px
    qy = ay + t * dy - py
    return qx * qx + qy * qy


@numba.njit(cache=True)
def _box_point_d2(xlo: float, ylo: float, xhi: float, yhi: float, px: float, py: float) -> float:
    qx = min(max(px, xlo), xhi) - px
    qy = min(max(py, ylo), yhi) - py
    return qx * qx + qy * qy


@numba.njit(cache=True)
def _seg_hits_box(ax: float, ay: float, bx: float, by: float,
                  xlo: float, ylo: float, xhi: float, yhi: float) -> bool:
    """Does segment a-b intersect the closed box (slab clipping)?"""
    t0 = 0.0
    t1 = 1.0
    d = (bx - ax, by - ay)
    p = (ax, ay)
    lo = (xlo, ylo)
    hi = (xhi, yhi)
    for k in range(2):
        if d[k] == 0.0:
            if p[k] < lo[k] or p[k] > hi[k]:
                return False
        else:
            u = (lo[k] - p[k]) / d[k]
            v = (hi[k] - p[k]) / d[k]
            if u > v:
                u, v = v, u
            t0 = max(t0, u)
            t1 = min(t1, v)
            if t0 > t1:
                return False
    return True


@numba.njit(cache=True)
def segment_clear(occ, h: int, w: int, cell: float, ax: float, ay: float, bx: float, by: float,
                  r: float) -> bool:
    """True if a disc of radius r swept from (ax, ay) to (bx, by) (world mm)
    stays inside the map and off every obstacle cell (distance >= r)."""
    for x, y in ((ax, ay), (bx, by)):  # the free area inside the border is convex
        if x < r or y < r or x > w * cell - r or y > h * cell - r:
            return False
    top = h * cell
    c0 = max(0, int(math.floor((min(ax, bx) - r) / cell)))
    c1 = min(w - 1, int(math.floor((max(ax, bx) + r) / cell)))
    r0 = max(0, int(math.floor((top - (max(ay, by) + r)) / cell)))
    r1 = min(h - 1, int(math.floor((top - (min(ay, by) - r)) / cell)))
    r2 = r * r
    for row in range(r0, r1 + 1):
        ylo = top - (row + 1) * cell
        yhi = ylo + cell
        for col in range(c0, c1 + 1):
            if not occ[row, col]:
                continue
            xlo = col * cell
            xhi = xlo + cell
            if _seg_hits_box(ax, ay, bx, by, xlo, ylo, xhi, yhi):
                return False
            # disjoint convex sets: the closest pair has a vertex of one of them
            d2 = min(_box_point_d2(xlo, ylo, xhi, yhi, ax, ay), _box_point_d2(xlo, ylo, xhi, yhi, bx, by))
            d2 = min(d2, _seg_point_d2(ax, ay, bx, by, xlo, ylo), _seg_point_d2(ax, ay, bx, by, xhi, ylo))
            d2 = min(d2, _seg_point_d2(ax, ay, bx, by, xlo, yhi), _seg_point_d2(ax, ay, bx, by, xhi, yhi))
            if d2 < r2:
                return False
    return True


@numba.njit(cache=True)
def cell_path(dist, occ, h: int, w: int, scol: int, srow: int, out) -> int:
    """Shortest 8-connected cell path from (scol, srow) down the goal's octile field `dist` into
    out ((col, row) rows, start and goal included); their count (0 if unreachable)."""
    if not dist[srow, scol] < np.inf:
        return 0
    col = scol
    row = srow
    n = 0
    # the goal is the cell at distance 0; its position breaks ties
    gcol = scol
    grow = srow
    for r in range(h):
        for c in range(w):
            if dist[r, c] == 0.0:
                gcol = c
                grow = r
    moves = np.empty((8, 3))
    while True:
        out[n, 0] = col
        out[n, 1] = row
        n += 1
        if dist[row, col] == 0.0 or n >= out.shape[0]:
            return n
        best_c = -1
        best_r = -1
        best_e = np.inf
        for k in range(octile_moves(occ, h, w, row, col, moves)):
            r = int(moves[k, 0])
            c = int(moves[k, 1])
            if dist[r, c] + moves[k, 2] > dist[row, col] + _TIE:
                continue  # not on a shortest path
            e = (c - gcol) * (c - gcol) + (r - grow) * (r - grow)
            if e < best_e:
                best_e = e
                best_c = c
                best_r = r
        if best_c < 0:  # cannot happen on a consistent field
            return 0
        col = best_c
        row = best_r


@numba.njit(cache=True)
def plan_into(occ, h: int, w: int, cell: float, dist, sx: float, sy: float, clear_r: float,
              max_seg: float, path, out) -> int:
    """Waypoints (world mm) from (sx, sy) to the goal of octile field `dist` into out (K, 2);
    their count, 0 if unreachable. `path` is scratch (>= H*W, 2)."""
    col = int(math.floor(sx / cell))
    row = h - 1 - int(math.floor(sy / cell))
    if col < 0 or row < 0 or col >= w or row >= h:
        return 0
    n = cell_path(dist, occ, h, w, col, row, path)
    if n == 0:
        return 0
    ax = sx
    ay = sy
    i = -1  # last path vertex taken
    k = 0
    while i < n - 1 and k < out.shape[0]:
        j_take = i + 1
        for j in range(n - 1, i, -1):
            vx = (path[j, 0] + 0.5) * cell
            vy = (h - path[j, 1] - 0.5) * cell
            if max_seg > 0.0 and j > i + 1 and math.hypot(vx - ax, vy - ay) > max_seg:
                continue
            if segment_clear(occ, h, w, cell, ax, ay, vx, vy, clear_r):
                j_take = j
                break
        ax = (path[j_take, 0] + 0.5) * cell
        ay = (h - path[j_take, 1] - 0.5) * cell
        out[k, 0] = ax
        out[k, 1] = ay
        k += 1
        i = j_take
    return k


@numba.njit(cache=True)
def remaining_lengths(wps, n: int, rem) -> None:
    """rem[k] = path length (mm) from waypoint k through the last one."""
    if n <= 0:
        return
    rem[n - 1] = 0.0
    for k in range(n - 2, -1, -1):
        rem[k] = rem[k + 1] + math.hypot(wps[k + 1, 0] - wps[k, 0], wps[k + 1, 1] - wps[k, 1])


def clearance_mm(margin_mm: float, radius_mm: float = robot_spec.ROBOT_RADIUS_MM) -> float:
    """The clearance a pruned segment keeps: the robot's body radius plus the margin."""
    return float(radius_mm) + float(margin_mm)


def profile_radius_mm(profile_file) -> float:
    """The body radius (mm) of a robot profile FILE.toml (None: the built-in robot's);
    ValueError (ProfileError) naming the file and key if it does not load."""
    if profile_file is None:
        return float(robot_spec.ROBOT_RADIUS_MM)
    from firmware_py.profile import load_profile

    return float(load_profile(profile_file).geometry.robot_radius_mm)


def guidance_from_metadata(meta: dict) -> dict:
    """plan_waypoints keywords (margin_mm, max_segment_mm) a sector policy was trained with, from
    a `.qtab`'s metadata or a run's meta.json; module defaults where absent."""
    cfg = meta.get("config") or {}
    return {"margin_mm": float(cfg.get("sector_margin_mm", meta.get("margin_mm", DEFAULT_MARGIN_MM))),
            "max_segment_mm": float(cfg.get("sector_max_segment_mm",
                                            meta.get("max_segment_mm", DEFAULT_MAX_SEGMENT_MM)))}


def plan_waypoints(gridmap: GridMap, start, goal: tuple[int, int], *, start_mm: bool = False,
                   margin_mm: float = DEFAULT_MARGIN_MM,
                   max_segment_mm: float = DEFAULT_MAX_SEGMENT_MM,
                   radius_mm: float = robot_spec.ROBOT_RADIUS_MM) -> list[tuple[int, int]]:
    """Mission waypoints [(x_mm, y_mm), ...] from `start` (a (col, row) cell, or with
    `start_mm=True` a world point) to the goal cell's centre for a body of `radius_mm`.
    MapError if the start or goal is blocked, off the map, or they are not connected."""
    occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
    h, w = occ.shape
    cell = float(gridmap.cell_size_m) * 1000.0
    gcol, grow = (int(v) for v in goal)
    if not gridmap.is_free(gcol, grow):
        raise MapError(f"goal ({gcol},{grow}) is not a free cell of map {gridmap.name}")
    if start_mm:
        sx, sy = (float(v) for v in start)
        if not (0.0 <= sx < w * cell and 0.0 <= sy < h * cell):
            raise MapError(f"start ({sx:g},{sy:g}) mm is off map {gridmap.name}")
        scol, srow = int(sx // cell), h - 1 - int(sy // cell)
    else:
        scol, srow = (int(v) for v in start)
        sx, sy = (scol + 0.5) * cell, (h - srow - 0.5) * cell
    if not gridmap.is_free(scol, srow):
        raise MapError(f"start cell ({scol},{srow}) is not a free cell of map {gridmap.name}")
    dist = octile_distances(gridmap.occ, gcol, grow)
    path = np.zeros((h * w, 2), dtype=np.int64)
    out = np.zeros((h * w, 2))
    n = plan_into(occ, h, w, cell, dist, sx, sy, clearance_mm(margin_mm, radius_mm), float(max_segment_mm), path, out)
    if n == 0:
        raise MapError(f"goal ({gcol},{grow}) cannot be reached from ({scol},{srow}) on map {gridmap.name}")
    return [(int(round(x)), int(round(y))) for x, y in out[:n]]
