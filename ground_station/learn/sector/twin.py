"""Kinematic twin of the robot on an occupancy grid, jitted (numba).

Owns the continuous-pose physics the `sector` encoding trains on: a disc of
`robot_spec.ROBOT_RADIUS_MM` driven by the action -> wheel-speed table for one
control period, exact collision against obstacle cells and the map border,
range sensors cast on the grid, and a jitted copy of the reference
`firmware_py.kinds.sector.encoder.SectorEncoder.encode` (tests prove it equals the
reference).

Conventions (all from `firmware_py.robot_spec`): world x east along columns, y
north, map row 0 is the northernmost row; heading counter-clockwise from +x.
Lengths are float millimetres, angles radians, except the encoder inputs
(int mm, int mrad) which are what the robot sees.

* Motion: constant wheel speeds over the control period give an exact arc;
  the pose is advanced in `PHYSICS_DT_US` substeps (the sim's dt) and the disc
  is checked for overlap with an obstacle cell or the border after each one
  (skipped when the start-of-period clearance already rules a hit out). A hit
  ends the motion at that substep and is reported; the episode ends there.
* Sensors: sensor i sits on the rim (`SENSOR_MOUNT_RADIUS_MM`) at angle
  `SENSOR_ANGLES_MRAD[i]`; its reading is the nearest hit of
  `SENSOR_FAN_RAYS` rays spread over `SENSOR_FOV_MRAD`, each cast exactly with
  a grid DDA (Amanatides-Woo). Status as the sim reports it: below
  `RANGE_MIN_MM` -> too close (range = min), beyond `RANGE_MAX_MM` -> too far
  (range = max), else valid with the distance rounded to whole mm.
* Progress potential: an estimate of the remaining shortest (octile) path
  length from a continuous position, used for shaped rewards, loop detection
  and evaluation.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from firmware_py import robot_spec

N_ACTIONS = len(robot_spec.ACTION_WHEEL_SPEEDS_MM_S)
ACTION_V_MM_S = np.array([(lw + rw) / 2.0 for lw, rw in robot_spec.ACTION_WHEEL_SPEEDS_MM_S])
ACTION_W_RAD_S = np.array([(rw - lw) / robot_spec.WHEEL_BASE_MM for lw, rw in robot_spec.ACTION_WHEEL_SPEEDS_MM_S])
N_SUBSTEPS = robot_spec.CONTROL_PERIOD_US // robot_spec.PHYSICS_DT_US
SUB_DT_S = robot_spec.PHYSICS_DT_US / 1e6
RADIUS_MM = float(robot_spec.ROBOT_RADIUS_MM)
MOUNT_MM = float(robot_spec.SENSOR_MOUNT_RADIUS_MM)
SENSOR_ANGLES_RAD = np.array(robot_spec.SENSOR_ANGLES_MRAD, dtype=np.float64) / 1000.0
if robot_spec.SENSOR_FAN_RAYS > 1:
    FAN_OFFSETS_RAD = (np.arange(robot_spec.SENSOR_FAN_RAYS) / (robot_spec.SENSOR_FAN_RAYS - 1) - 0.5) * (
        robot_spec.SENSOR_FOV_MRAD / 1000.0)
else:
    FAN_OFFSETS_RAD = np.zeros(1)
_SENS_COS = np.cos(SENSOR_ANGLES_RAD)
_SENS_SIN = np.sin(SENSOR_ANGLES_RAD)
_RAY_COS = np.cos(SENSOR_ANGLES_RAD[:, None] + FAN_OFFSETS_RAD[None, :])
_RAY_SIN = np.sin(SENSOR_ANGLES_RAD[:, None] + FAN_OFFSETS_RAD[None, :])
RANGE_MIN = robot_spec.RANGE_MIN_MM
RANGE_MAX = robot_spec.RANGE_MAX_MM
GOAL_TOL_MM = float(robot_spec.GOAL_TOLERANCE_MM)
TWO_PI_MRAD = 6283  # the reference encoder's 2*pi; asserted equal in the tests
# Largest distance the disc centre can travel in one control period (any action).
MAX_MOVE_MM = float(np.max(np.abs(ACTION_V_MM_S))) * N_SUBSTEPS * SUB_DT_S + 1e-6


# --- geometry ----------------------------------------------------------------

@numba.njit(cache=True, inline="always")
def cell_of(x: float, y: float, h: int, cell: float) -> tuple[int, int]:
    """(col, row) of the cell containing world point (x, y) mm."""
    return int(math.floor(x / cell)), h - 1 - int(math.floor(y / cell))


@numba.njit(cache=True, inline="always")
def cell_centre(col: int, row: int, h: int, cell: float) -> tuple[float, float]:
    return (col + 0.5) * cell, (h - row - 0.5) * cell


@numba.njit(cache=True, inline="always")
def disc_hits(occ, h: int, w: int, cell: float, x: float, y: float, r: float) -> bool:
    """True if the open disc (x, y, r) overlaps an obstacle cell or leaves the map."""
    if x < r or y < r or x > w * cell - r or y > h * cell - r:
        return True
    c0 = max(0, int(math.floor((x - r) / cell)))
    c1 = min(w - 1, int(math.floor((x + r) / cell)))
    top = h * cell  # world y of the north edge of row 0
    r0 = max(0, int(math.floor((top - (y + r)) / cell)))
    r1 = min(h - 1, int(math.floor((top - (y - r)) / cell)))
    r2 = r * r
    for row in range(r0, r1 + 1):
        ylo = top - (row + 1) * cell
        yhi = ylo + cell
        for col in range(c0, c1 + 1):
            if not occ[row, col]:
                continue
            xlo = col * cell
            px = min(max(x, xlo), xlo + cell)
            py = min(max(y, ylo), yhi)
            dx = x - px
            dy = y - py
            if dx * dx + dy * dy < r2:
                return True
    return False


@numba.njit(cache=True, inline="always")
def move(occ, h: int, w: int, cell: float, x: float, y: float, th: float, action: int):
    """Hold `action` for one control period from pose (x, y, th).

    Returns (x, y, th, driven_mm, hit). On a hit the pose is the first
    substep pose that overlaps an obstacle."""
    v = ACTION_V_MM_S[action]
    om = ACTION_W_RAD_S[action]
    check = v != 0.0 and disc_hits(occ, h, w, cell, x, y, RADIUS_MM + MAX_MOVE_MM)
    if not check:  # no contact possible this period: the exact arc in one go
        t = N_SUBSTEPS * SUB_DT_S
        if om == 0.0:
            return x + v * t * math.cos(th), y + v * t * math.sin(th), th, abs(v) * t, False
        th2 = th + om * t
        x += v / om * (math.sin(th2) - math.sin(th))
        y -= v / om * (math.cos(th2) - math.cos(th))
        return x, y, wrap_angle(th2), abs(v) * t, False
    driven = 0.0
    # sin/cos of the substep's start heading are the previous substep's end values
    s0 = math.sin(th)
    c0 = math.cos(th)
    for _ in range(N_SUBSTEPS):
        if om == 0.0:
            x += v * SUB_DT_S * c0
            y += v * SUB_DT_S * s0
            th2 = th
        else:
            th2 = th + om * SUB_DT_S
            s1 = math.sin(th2)
            c1 = math.cos(th2)
            x += v / om * (s1 - s0)
            y -= v / om * (c1 - c0)
            s0 = s1
            c0 = c1
        th = th2
        driven += abs(v) * SUB_DT_S
        if disc_hits(occ, h, w, cell, x, y, RADIUS_MM):
            return x, y, wrap_angle(th), driven, True
    return x, y, wrap_angle(th), driven, False


@numba.njit(cache=True, inline="always")
def wrap_angle(a: float) -> float:
    """Angle in [-pi, pi): (a + pi) % 2pi - pi with Python's float modulo.

    The usual cases skip the modulo's library call with the very number it
    returns: for 0 <= x < 2pi it is x; for 2pi <= x < 4pi, fmod's exact
    x - 2pi (Sterbenz: the subtraction is exact); for -2pi <= x < 0, fmod
    gives x and Python adds 2pi (the same rounded sum)."""
    x = a + math.pi
    b = 2.0 * math.pi
    if x >= 0.0:
        if x < b:
            r = x
        elif x < 2.0 * b:
            r = x - b
        else:
            r = x % b
    elif x >= -b:
        r = x + b
    else:
        r = x % b
    return r - math.pi


@numba.njit(cache=True)
def ray_cast(occ, h: int, w: int, cell: float, ox: float, oy: float, ang: float, maxd: float) -> float:
    """Distance (mm) from (ox, oy) along `ang` to the first obstacle cell or
    the map border; `maxd` if nothing is hit within maxd. Exact grid DDA."""
    return ray_cast_dir(occ, h, w, cell, ox, oy, math.cos(ang), math.sin(ang), maxd)


@numba.njit(cache=True, inline="always")
def _dda_axis(d: float, pos: float, idx: int, cell: float):
    """One axis of the grid DDA: (cell step, ray length per cell, ray length to
    the first cell boundary) for direction component d at grid position pos
    inside cell idx."""
    if d > 0.0:
        t_delta = cell / d
        return 1, t_delta, (idx + 1 - pos) * t_delta
    if d < 0.0:
        t_delta = -cell / d
        return -1, t_delta, (pos - idx) * t_delta
    return 0, np.inf, np.inf


@numba.njit(cache=True)
def ray_cast_dir(occ, h: int, w: int, cell: float, ox: float, oy: float, cx: float, cy: float,
                 maxd: float) -> float:
    """`ray_cast` with the unit direction (cx, cy) given instead of the angle."""
    # grid coordinates: u along columns, v along rows (south)
    u = ox / cell
    vv = (h * cell - oy) / cell
    du = cx
    dv = -cy
    col = int(math.floor(u))
    row = int(math.floor(vv))
    if col < 0 or row < 0 or col >= w or row >= h or occ[row, col]:
        return 0.0
    sc, tdu, tmu = _dda_axis(du, u, col, cell)
    sr, tdv, tmv = _dda_axis(dv, vv, row, cell)
    while True:
        if tmu < tmv:
            t = tmu
            col += sc
            tmu += tdu
        else:
            t = tmv
            row += sr
            tmv += tdv
        if t > maxd:
            return maxd
        if col < 0 or row < 0 or col >= w or row >= h or occ[row, col]:
            return t


@numba.njit(cache=True, inline="always")
def _reading(d: float):
    if d < RANGE_MIN:
        return RANGE_MIN, robot_spec.RANGE_TOO_CLOSE
    if d > RANGE_MAX:
        return RANGE_MAX, robot_spec.RANGE_TOO_FAR
    return int(math.floor(d + 0.5)), robot_spec.RANGE_VALID


@numba.njit(cache=True)
def sense_one(occ, h: int, w: int, cell: float, x: float, y: float, th: float, i: int):
    """(range_mm, status) of sensor i at pose (x, y, th), as the sim reports it."""
    a = th + SENSOR_ANGLES_RAD[i]
    ox = x + MOUNT_MM * math.cos(a)
    oy = y + MOUNT_MM * math.sin(a)
    d = np.inf
    for k in range(FAN_OFFSETS_RAD.shape[0]):
        t = ray_cast(occ, h, w, cell, ox, oy, a + FAN_OFFSETS_RAD[k], RANGE_MAX + 1.0)
        if t < d:
            d = t
    return _reading(d)


@numba.njit(cache=True, inline="always")
def fan_ray(x: float, y: float, ct: float, st: float, i: int, k: int) -> tuple[float, float, float, float]:
    """Origin (ox, oy) and unit direction (cx, cy) of ray k of sensor i's fan, the robot at
    (x, y) with heading cos/sin (ct, st): the fixed angles' trigonometry is precomputed."""
    ox = x + MOUNT_MM * (ct * _SENS_COS[i] - st * _SENS_SIN[i])
    oy = y + MOUNT_MM * (st * _SENS_COS[i] + ct * _SENS_SIN[i])
    cx = ct * _RAY_COS[i, k] - st * _RAY_SIN[i, k]
    cy = st * _RAY_COS[i, k] + ct * _RAY_SIN[i, k]
    return ox, oy, cx, cy


@numba.njit(cache=True, inline="always")
def fan_distance(occ, h: int, w: int, cell: float, x: float, y: float, ct: float, st: float, i: int) -> float:
    """Sensor i's distance to the map's cells (its fan's nearest hit, at most RANGE_MAX + 1),
    before `_reading` turns it into a range and status; see `sense` for the cast lengths."""
    d = RANGE_MAX + 1.0
    for k in range(_RAY_COS.shape[1]):
        ox, oy, cx, cy = fan_ray(x, y, ct, st, i, k)
        t = ray_cast_dir(occ, h, w, cell, ox, oy, cx, cy, d)
        if t < d:
            d = t
    return d


@numba.njit(cache=True)
def sense(occ, h: int, w: int, cell: float, x: float, y: float, th: float, which, ranges, status) -> None:
    """Fill ranges/status (int64, length SENSOR_COUNT) for the sensors whose
    `which` flag is set; the others are left untouched. Same readings as
    `sense_one`, with the trigonometry of the fixed angles precomputed.

    A fan's later rays are cast only as far as the nearest hit so far: a
    cast to maxd returns min(hit distance, maxd) with the hit distance
    computed the same way whatever maxd is, so the fan's minimum is the
    same number (bit for bit) as casting every ray to the full range."""
    ct = math.cos(th)
    st = math.sin(th)
    for i in range(ranges.shape[0]):
        if which[i]:
            ranges[i], status[i] = _reading(fan_distance(occ, h, w, cell, x, y, ct, st, i))


def bordered(occ: np.ndarray, h: int, w: int) -> np.ndarray:
    """occ[:h, :w] (uint8) inside a one-cell frame of obstacles, shape (h + 2, w + 2):
    cell (row, col) of the map is [row + 1, col + 1]; everything off the map
    reads as an obstacle. `sense_bordered` takes it."""
    out = np.ones((h + 2, w + 2), dtype=np.uint8)
    out[1:h + 1, 1:w + 1] = occ[:h, :w]
    return out


@numba.njit(cache=True, inline="always")
def _cast_bordered(occb, u: float, vv: float, col: int, row: int, du: float, dv: float, cell: float,
                   maxd: float) -> float:
    """The DDA of `ray_cast_dir` on a bordered grid from a free origin cell:
    the same sums in the same order (the same distance bit for bit), with
    the map border read from the frame instead of four bound checks per cell
    (the ray enters a frame cell before it could leave the frame)."""
    sc, tdu, tmu = _dda_axis(du, u, col, cell)
    sr, tdv, tmv = _dda_axis(dv, vv, row, cell)
    while True:
        # branch-free step (selects, not jumps: which axis steps next is
        # unpredictable); adding 0.0 leaves the other axis' sum unchanged
        cu = tmu < tmv
        t = tmu if cu else tmv
        col += sc if cu else 0
        row += 0 if cu else sr
        tmu += tdu if cu else 0.0
        tmv += 0.0 if cu else tdv
        if t > maxd:
            return maxd
        if occb[row + 1, col + 1]:
            return t


@numba.njit(cache=True, inline="always")
def sense_bordered(occb, h: int, w: int, cell: float, x: float, y: float, th: float, which, ranges,
                   status) -> None:
    """`sense` on a `bordered` occupancy grid: the same readings bit for bit
    (tests compare them), faster (the fan's rays share their origin cell, no
    bound checks in the DDA). The trainer's hot loop uses it."""
    ct = math.cos(th)
    st = math.sin(th)
    top = h * cell
    for i in range(ranges.shape[0]):
        if not which[i]:
            continue
        ox = x + MOUNT_MM * (ct * _SENS_COS[i] - st * _SENS_SIN[i])
        oy = y + MOUNT_MM * (st * _SENS_COS[i] + ct * _SENS_SIN[i])
        u = ox / cell
        vv = (top - oy) / cell
        col = int(math.floor(u))
        row = int(math.floor(vv))
        if col < 0 or row < 0 or col >= w or row >= h or occb[row + 1, col + 1]:
            ranges[i], status[i] = _reading(0.0)
            continue
        d = RANGE_MAX + 1.0
        for k in range(_RAY_COS.shape[1]):
            cx = ct * _RAY_COS[i, k] - st * _RAY_SIN[i, k]
            cy = st * _RAY_COS[i, k] + ct * _RAY_SIN[i, k]
            t = _cast_bordered(occb, u, vv, col, row, cx, -cy, cell, d)
            if t < d:
                d = t
        ranges[i], status[i] = _reading(d)


@numba.njit(cache=True, inline="always")
def bearing_mrad(x: float, y: float, th: float, gx: float, gy: float) -> int:
    """Goal bearing relative to the heading, int mrad in about [-3142, 3142]."""
    b = wrap_angle(math.atan2(gy - y, gx - x) - th)
    return int(math.floor(b * 1000.0 + 0.5))


@numba.njit(cache=True)
def potential(dist, occ, h: int, w: int, cell: float, x: float, y: float) -> float:
    """Remaining path length estimate (mm) from (x, y) to the goal whose
    octile distance field (cells) is `dist`: the best of the free 8-neighbour
    cell centres reachable without corner cutting (and the own cell) of
    distance-to-centre + the centre's octile distance. Continuous up to small
    jumps at cell borders; exactly the Euclidean distance next to the goal."""
    col, row = cell_of(x, y, h, cell)
    best = np.inf
    for dr in range(-1, 2):
        for dc in range(-1, 2):
            r = row + dr
            c = col + dc
            if r < 0 or c < 0 or r >= h or c >= w or occ[r, c]:
                continue
            if dr != 0 and dc != 0 and (occ[row + dr, col] or occ[row, col + dc]):
                continue  # no corner cutting, as the octile field
            d = dist[r, c]
            if not d < np.inf:
                continue
            cx, cy = cell_centre(c, r, h, cell)
            val = d * cell + math.sqrt((x - cx) * (x - cx) + (y - cy) * (y - cy))
            if val < best:
                best = val
    return best


# --- fast encoder (copy of firmware_py.kinds.sector.encoder.SectorEncoder.encode) -------

@numba.njit(cache=True, inline="always")
def bearing_sector_fast(bearing_mrad: int, sectors: int) -> int:
    b = bearing_mrad % TWO_PI_MRAD
    return ((2 * b * sectors + TWO_PI_MRAD) // (2 * TWO_PI_MRAD)) % sectors


@numba.njit(cache=True, inline="always")
def encode_fast(bearing_mrad: int, ranges, status, sectors: int, sensors, edges) -> int:
    """Same index as SectorEncoder(sectors, sensors, edges).encode(bearing, ranges, status)."""
    nb = edges.shape[0] + 1
    state = 0
    mult = 1
    for j in range(sensors.shape[0]):
        s = sensors[j]
        st = status[s]
        if st == robot_spec.RANGE_TOO_CLOSE:
            b = 0
        elif st != robot_spec.RANGE_VALID:
            b = nb - 1
        else:
            b = 0
            for e in range(edges.shape[0]):
                if ranges[s] >= edges[e]:
                    b += 1
        state += b * mult
        mult *= nb
    return bearing_sector_fast(bearing_mrad, sectors) * mult + state


def encoder_arrays(encoder) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """(bearing_sectors, sensors, range_edges, sensor-needed flags) as the
    kernels take them, from a `SectorEncoder`."""
    sensors = np.asarray(encoder.sensors, dtype=np.int64)
    edges = np.asarray(encoder.range_edges_mm, dtype=np.int64)
    which = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.bool_)
    which[sensors] = True
    return int(encoder.bearing_sectors), sensors, edges, which


def grid_of(gridmap) -> tuple[np.ndarray, int, int, float]:
    """(occ uint8 (H, W), H, W, cell_mm) of a GridMap, as the kernels take them."""
    occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
    return occ, int(occ.shape[0]), int(occ.shape[1]), float(gridmap.cell_size_m) * 1000.0

