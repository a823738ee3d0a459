"""Unmapped obstacles: discs and movers the planner does not know, placed so a detour exists.

The one definition of the discs and movers `qnav demo --obstacles/--movers`
sends to the sim and the benchmark's scenario episodes are made of; its
configuration-space raster is also the one `nav.replan` plans on.

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
   detour exists (so never in a one-cell corridor). Where no position passes
   after `TRIES` draws, fewer than k discs are placed.

**Movers** are discs of `MOVER_RADIUS_MM` walking straight lines at a
pedestrian's slow pace (`MOVER_SPEED_MM_S`, uniform in that range, random
direction), starting in free space at least `MOVER_START_MM` from the robot,
bouncing off walls, discs and the robot (`sim_bridge.obstacles.step_movers`).
"""

from __future__ import annotations

import math

import numpy as np

from firmware_py import robot_spec
from ground_station.jitcache import numba
from ground_station.learn.sector.twin import disc_hits
from ground_station.maps import GridMap, octile_distances

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


# --- configuration space ---------------------------------------------------------

@numba.njit(cache=True)
def cspace(occ, cell, discs, step, clear):
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


def _raster_point(free: np.ndarray, x: float, y: float) -> tuple[int, int]:
    ny, nx = free.shape
    return min(nx - 1, max(0, int(x // RASTER_MM))), min(ny - 1, max(0, int(y // RASTER_MM)))


def raster_nearest(free: np.ndarray, x: float, y: float, reach: int = 3) -> tuple[int, int] | None:
    """Nearest free raster point to (x, y) mm within `reach` raster steps (None if there is none)."""
    ny, nx = free.shape
    ix, iy = _raster_point(free, x, y)
    if free[iy, ix]:
        return ix, iy
    best, pick = math.inf, None
    for yy in range(max(0, iy - reach), min(ny, iy + reach + 1)):
        for xx in range(max(0, ix - reach), min(nx, ix + reach + 1)):
            if free[yy, xx]:
                d = (xx - ix) ** 2 + (yy - iy) ** 2
                if d < best:
                    best, pick = d, (xx, yy)
    return pick


def raster_index(free: np.ndarray, x: float, y: float) -> tuple[int, int]:
    """Nearest free raster point to (x, y) mm (the point itself when free, or when none is near)."""
    return raster_nearest(free, x, y) or _raster_point(free, x, y)


def _leg_lengths(gridmap: GridMap, points: list[tuple[float, float]], discs: np.ndarray,
                 margin: float = CSPACE_MARGIN_MM) -> list[float]:
    occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
    cell = gridmap.cell_size_m * 1000.0
    free = cspace(occ, cell, discs.reshape(-1, 3), RASTER_MM, robot_spec.ROBOT_RADIUS_MM + margin)
    return _raster_legs(free, points)


def _raster_legs(free: np.ndarray, points: list[tuple[float, float]]) -> list[float]:
    """Shortest 8-connected raster path (mm) of each leg points[i] -> points[i+1] on `free`."""
    out = []
    for a, b in zip(points[:-1], points[1:], strict=True):
        ia, ib = raster_index(free, *a), raster_index(free, *b)
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
        if disc_blocked(occ, cell, x, y, r):
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


def disc_blocked(occ: np.ndarray, cell: float, x: float, y: float, r: float) -> bool:
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


def point_along(points: list[tuple[float, float]], s: float) -> tuple[float, float, float]:
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
            x, y, ang = point_along(points, float(rng.uniform(0.15, 0.85)) * total)
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
            if math.hypot(x - start[0], y - start[1]) < MOVER_START_MM or disc_blocked(occ, cell, x, y, r):
                continue
            if any(math.hypot(x - dx, y - dy) < r + dr for dx, dy, dr in discs):
                continue
            v = float(rng.uniform(*speed))
            a = float(rng.uniform(-math.pi, math.pi))
            out.append((round(x, 1), round(y, 1), round(v * math.cos(a), 1), round(v * math.sin(a), 1), r,
                        1.0 if yields else 0.0))
            break
    return out
