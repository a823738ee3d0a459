"""Kinematic twin of the robot on an occupancy grid, jitted (numba).

Owns the continuous-pose physics the `sector` encoding trains on: a disc of the
robot's body radius driven by each action's wheel speeds for one control period,
exact collision against obstacle cells and the map border, range sensors cast on
the grid, and a jitted copy of `SectorEncoder.encode` (tests prove them equal).
Every kernel takes the robot as one tuple of arrays `tw` (`TwinRobot.arrays`),
never as module globals, so one compiled kernel trains any robot.

Conventions (`firmware_py.robot_spec`): x east along columns, y north, map row 0
northernmost, heading counter-clockwise from +x; float mm and radians, except
the encoder inputs (int mm, int mrad), which are what the robot sees.

* Motion: constant wheel speeds over the control period give an exact arc,
  advanced in `PHYSICS_DT_US` substeps (the sim's dt) with an overlap check
  after each (skipped when the start-of-period clearance rules a hit out); a
  hit ends the motion at that substep, and the episode.
* Sensors: sector i is read by the sensor on the rim at `TwinRobot.angles_mrad[i]`:
  the nearest hit of `SENSOR_FAN_RAYS` rays over `SENSOR_FOV_MRAD`, each cast
  with an exact grid DDA (Amanatides-Woo). Status as the sim reports it: below
  `RANGE_MIN_MM` too close (range = min), beyond the reach too far (range =
  reach), else valid in whole mm; a sector no sensor covers reads INVALID.
* Progress potential: the remaining shortest (octile) path length from a
  continuous position (shaped rewards, loop detection, evaluation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware_py import robot_spec
from firmware_py.layout import Layout
from firmware_py.needs import DEFAULT as DEFAULT_TRAINED
from firmware_py.needs import TrainedFor
from ground_station.jitcache import numba

N_ACTIONS = len(robot_spec.ACTION_WHEEL_SPEEDS_MM_S)
N_SUBSTEPS = robot_spec.CONTROL_PERIOD_US // robot_spec.PHYSICS_DT_US
SUB_DT_S = robot_spec.PHYSICS_DT_US / 1e6
if robot_spec.SENSOR_FAN_RAYS > 1:
    FAN_OFFSETS_RAD = (np.arange(robot_spec.SENSOR_FAN_RAYS) / (robot_spec.SENSOR_FAN_RAYS - 1) - 0.5) * (
        robot_spec.SENSOR_FOV_MRAD / 1000.0)
else:
    FAN_OFFSETS_RAD = np.zeros(1)
RANGE_MIN = robot_spec.RANGE_MIN_MM
GOAL_TOL_MM = float(robot_spec.GOAL_TOLERANCE_MM)
TWO_PI_MRAD = 6283  # the reference encoder's 2*pi; asserted equal in the tests


# --- the robot the twin plays (a robot profile) --------------------------------

@dataclass(frozen=True)
class TwinRobot:
    """The robot the twin plays, from a robot profile (default: the built-in robot): body radius
    (the disc, the sensors' rim), wheel base, wheel speed limit (clamped as the controller
    clamps), and the eight sectors as the robot reads them (`Layout.sector_layout`; a sector no
    sensor covers reads INVALID, range 0). Wheel radius and encoder counts do not enter (mm/s)."""

    radius_mm: int = robot_spec.ROBOT_RADIUS_MM
    wheel_base_mm: int = robot_spec.WHEEL_BASE_MM
    max_speed_mm_s: int = robot_spec.MAX_WHEEL_SPEED_MM_S
    angles_mrad: tuple[int, ...] = robot_spec.SENSOR_ANGLES_MRAD
    ranges_mm: tuple[int, ...] = (robot_spec.RANGE_MAX_MM,) * robot_spec.SENSOR_COUNT
    source: str = "built-in default"

    @classmethod
    def of_profile(cls, profile=None) -> TwinRobot:  # type: ignore[no-untyped-def]
        """The twin of a `firmware_py.profile.RobotProfile` (None: the built-in robot)."""
        if profile is None:
            return cls()
        return cls.of_trained(TrainedFor.of_profile(profile))

    @classmethod
    def of_trained(cls, t: TrainedFor) -> TwinRobot:
        """The twin of the robot a policy was trained for (a run's meta.json `robot`): a sector no
        sensor covers at its built-in angle, reach 0 (INVALID)."""
        if t == DEFAULT_TRAINED:
            return cls()
        angles = tuple(robot_spec.SENSOR_ANGLES_MRAD[k] if a is None else a for k, a in enumerate(t.sector_angles_mrad))
        ranges = tuple(0 if a is None else r for a, r in zip(t.sector_angles_mrad, t.sector_ranges_mm, strict=True))
        return cls(radius_mm=t.robot_radius_mm, wheel_base_mm=t.wheel_base_mm, max_speed_mm_s=t.wheel_speed_mm_s,
                   angles_mrad=angles, ranges_mm=ranges, source=t.source)

    @classmethod
    def of_meta(cls, meta: dict) -> TwinRobot:
        """The robot a training run's meta.json records (`robot`; a run without one: the built-in
        robot); ValueError (one line) if the record is malformed."""
        rec = meta.get("robot")
        return cls() if rec is None else cls.of_trained(TrainedFor.from_dict(rec))

    def layout(self) -> Layout:
        """The robot's `Layout`: the eight sectors at the twin's angles (an uncovered one at the
        farthest reach; it reads INVALID)."""
        reach = max(self.ranges_mm)
        return Layout(robot_radius_mm=self.radius_mm, wheel_base_mm=self.wheel_base_mm,
                      max_wheel_speed_mm_s=self.max_speed_mm_s, angles_mrad=tuple(self.angles_mrad),
                      max_ranges_mm=tuple(r or reach for r in self.ranges_mm))

    def wheel_speeds(self) -> tuple[tuple[int, int], ...]:
        """Each action's (left, right) wheel speeds as the robot drives them (clamped to its limit)."""
        lim = self.max_speed_mm_s
        return tuple((max(-lim, min(lim, lw)), max(-lim, min(lim, rw))) for lw, rw in robot_spec.ACTION_WHEEL_SPEEDS_MM_S)

    def arrays(self) -> tuple:
        """The tuple `tw` every kernel takes (slots TW_*): what `move` and the sensors read of the robot."""
        speeds = self.wheel_speeds()
        act_v = np.array([(lw + rw) / 2.0 for lw, rw in speeds])
        act_w = np.array([(rw - lw) / self.wheel_base_mm for lw, rw in speeds])
        ang = np.array(self.angles_mrad, dtype=np.float64) / 1000.0
        max_move = float(np.max(np.abs(act_v))) * N_SUBSTEPS * SUB_DT_S + 1e-6
        fwd = float(np.max(act_v)) * N_SUBSTEPS * SUB_DT_S
        geo = np.array([float(self.radius_mm), float(self.radius_mm), max_move, fwd])
        return (geo, act_v, act_w, ang, np.cos(ang), np.sin(ang), np.cos(ang[:, None] + FAN_OFFSETS_RAD[None, :]),
                np.sin(ang[:, None] + FAN_OFFSETS_RAD[None, :]), np.array(self.ranges_mm, dtype=np.float64))


# slots of the `tw` tuple (TwinRobot.arrays) and of its first array (G_*)
TW_GEO, TW_V, TW_W, TW_ANG, TW_SCOS, TW_SSIN, TW_RCOS, TW_RSIN, TW_RMAX = range(9)
G_RADIUS, G_MOUNT, G_MAX_MOVE, G_FWD = range(4)

DEFAULT_TW = TwinRobot().arrays()  # the built-in robot's
# the built-in robot's figures (tests, and the callers that have no profile)
ACTION_V_MM_S = DEFAULT_TW[TW_V]
ACTION_W_RAD_S = DEFAULT_TW[TW_W]
RADIUS_MM = float(robot_spec.ROBOT_RADIUS_MM)
MAX_MOVE_MM = float(DEFAULT_TW[TW_GEO][G_MAX_MOVE])


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
def move(occ, h: int, w: int, cell: float, x: float, y: float, th: float, action: int, tw):
    """Hold `action` for one control period from pose (x, y, th): (x, y, th, driven_mm, hit);
    on a hit the pose is the first substep pose that overlaps an obstacle."""
    v = tw[TW_V][action]
    om = tw[TW_W][action]
    radius = tw[TW_GEO][G_RADIUS]
    check = v != 0.0 and disc_hits(occ, h, w, cell, x, y, radius + tw[TW_GEO][G_MAX_MOVE])
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
        if disc_hits(occ, h, w, cell, x, y, radius):
            return x, y, wrap_angle(th), driven, True
    return x, y, wrap_angle(th), driven, False


@numba.njit(cache=True, inline="always")
def wrap_angle(a: float) -> float:
    """Angle in [-pi, pi): (a + pi) % 2pi - pi with Python's float modulo, the usual cases
    without the library call but with the very number it returns (x - 2pi is exact, Sterbenz)."""
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
    """Distance (mm) from (ox, oy) along `ang` to the first obstacle cell or the border (at most maxd)."""
    return ray_cast_dir(occ, h, w, cell, ox, oy, math.cos(ang), math.sin(ang), maxd)


@numba.njit(cache=True, inline="always")
def _dda_axis(d: float, pos: float, idx: int, cell: float):
    """One axis of the grid DDA for direction component d at grid position pos in cell idx:
    (cell step, ray length per cell, ray length to the first cell boundary)."""
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
def _reading(d: float, rmax: float):
    """(range, status) of a fan's nearest hit d for a sensor of reach rmax (0: no sensor, INVALID)."""
    if rmax <= 0.0:
        return 0, robot_spec.RANGE_INVALID
    if d < RANGE_MIN:
        return RANGE_MIN, robot_spec.RANGE_TOO_CLOSE
    if d > rmax:
        return int(rmax), robot_spec.RANGE_TOO_FAR
    return int(math.floor(d + 0.5)), robot_spec.RANGE_VALID


@numba.njit(cache=True)
def sense_one(occ, h: int, w: int, cell: float, x: float, y: float, th: float, i: int, tw):
    """(range_mm, status) of sensor i of the robot `tw` at pose (x, y, th), as the sim reports it."""
    a = th + tw[TW_ANG][i]
    mount = tw[TW_GEO][G_MOUNT]
    ox = x + mount * math.cos(a)
    oy = y + mount * math.sin(a)
    d = np.inf
    for k in range(FAN_OFFSETS_RAD.shape[0]):
        t = ray_cast(occ, h, w, cell, ox, oy, a + FAN_OFFSETS_RAD[k], tw[TW_RMAX][i] + 1.0)
        if t < d:
            d = t
    return _reading(d, tw[TW_RMAX][i])


@numba.njit(cache=True, inline="always")
def fan_ray(x: float, y: float, ct: float, st: float, i: int, k: int, tw) -> tuple[float, float, float, float]:
    """Origin (ox, oy) and unit direction (cx, cy) of ray k of sensor i's fan at (x, y), heading
    cos/sin (ct, st)."""
    mount = tw[TW_GEO][G_MOUNT]
    sc = tw[TW_SCOS][i]
    ss = tw[TW_SSIN][i]
    rc = tw[TW_RCOS][i, k]
    rs = tw[TW_RSIN][i, k]
    ox = x + mount * (ct * sc - st * ss)
    oy = y + mount * (st * sc + ct * ss)
    cx = ct * rc - st * rs
    cy = st * rc + ct * rs
    return ox, oy, cx, cy


@numba.njit(cache=True, inline="always")
def fan_distance(occ, h: int, w: int, cell: float, x: float, y: float, ct: float, st: float, i: int,
                 tw) -> float:
    """Sensor i's fan's nearest hit (at most its reach + 1), before `_reading`; cast lengths: `sense`."""
    d = tw[TW_RMAX][i] + 1.0
    for k in range(tw[TW_RCOS].shape[1]):
        ox, oy, cx, cy = fan_ray(x, y, ct, st, i, k, tw)
        t = ray_cast_dir(occ, h, w, cell, ox, oy, cx, cy, d)
        if t < d:
            d = t
    return d


@numba.njit(cache=True)
def sense(occ, h: int, w: int, cell: float, x: float, y: float, th: float, which, ranges, status, tw) -> None:
    """Fill ranges/status (int64, SENSOR_COUNT) of the sensors whose `which` flag is set (others
    untouched): `sense_one`'s readings, the fixed angles' trigonometry precomputed. A fan's later
    rays are cast only as far as the nearest hit so far: the hit distance does not depend on maxd,
    so the minimum is bit for bit that of casting every ray to the full range."""
    ct = math.cos(th)
    st = math.sin(th)
    for i in range(ranges.shape[0]):
        if which[i]:
            ranges[i], status[i] = _reading(fan_distance(occ, h, w, cell, x, y, ct, st, i, tw), tw[TW_RMAX][i])


def bordered(occ: np.ndarray, h: int, w: int) -> np.ndarray:
    """occ[:h, :w] (uint8) in a one-cell frame of obstacles (h + 2, w + 2) for `sense_bordered`:
    map cell (row, col) is [row + 1, col + 1]."""
    out = np.ones((h + 2, w + 2), dtype=np.uint8)
    out[1:h + 1, 1:w + 1] = occ[:h, :w]
    return out


@numba.njit(cache=True, inline="always")
def _cast_bordered(occb, u: float, vv: float, col: int, row: int, du: float, dv: float, cell: float,
                   maxd: float) -> float:
    """`ray_cast_dir`'s DDA (same sums, same order: bit for bit) on a bordered grid from a free
    origin cell, the map border read from the frame instead of four bound checks per cell."""
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
                   status, tw) -> None:
    """`sense` on a `bordered` grid, the same readings bit for bit, faster (the trainer's hot loop)."""
    ct = math.cos(th)
    st = math.sin(th)
    top = h * cell
    mount = tw[TW_GEO][G_MOUNT]
    scos, ssin, rcos, rsin, rmax = tw[TW_SCOS], tw[TW_SSIN], tw[TW_RCOS], tw[TW_RSIN], tw[TW_RMAX]
    for i in range(ranges.shape[0]):
        if not which[i]:
            continue
        if rmax[i] <= 0.0:
            ranges[i], status[i] = _reading(0.0, rmax[i])
            continue
        ox = x + mount * (ct * scos[i] - st * ssin[i])
        oy = y + mount * (st * scos[i] + ct * ssin[i])
        u = ox / cell
        vv = (top - oy) / cell
        col = int(math.floor(u))
        row = int(math.floor(vv))
        if col < 0 or row < 0 or col >= w or row >= h or occb[row + 1, col + 1]:
            ranges[i], status[i] = _reading(0.0, rmax[i])
            continue
        d = rmax[i] + 1.0
        for k in range(rcos.shape[1]):
            cx = ct * rcos[i, k] - st * rsin[i, k]
            cy = st * rcos[i, k] + ct * rsin[i, k]
            t = _cast_bordered(occb, u, vv, col, row, cx, -cy, cell, d)
            if t < d:
                d = t
        ranges[i], status[i] = _reading(d, rmax[i])


@numba.njit(cache=True, inline="always")
def bearing_mrad(x: float, y: float, th: float, gx: float, gy: float) -> int:
    """Goal bearing relative to the heading, int mrad in about [-3142, 3142]."""
    b = wrap_angle(math.atan2(gy - y, gx - x) - th)
    return int(math.floor(b * 1000.0 + 0.5))


@numba.njit(cache=True)
def potential(dist, occ, h: int, w: int, cell: float, x: float, y: float) -> float:
    """Remaining path length estimate (mm) to the goal of octile field `dist` (cells): the least
    distance-to-centre + the centre's octile distance over the own cell and the free 8-neighbours
    reachable without corner cutting. Continuous up to small jumps at cell borders; Euclidean next
    to the goal."""
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
    """(bearing_sectors, sensors, range_edges, sensor-needed flags) of a `SectorEncoder`."""
    sensors = np.asarray(encoder.sensors, dtype=np.int64)
    edges = np.asarray(encoder.range_edges_mm, dtype=np.int64)
    which = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.bool_)
    which[sensors] = True
    return int(encoder.bearing_sectors), sensors, edges, which


def grid_of(gridmap) -> tuple[np.ndarray, int, int, float]:
    """(occ uint8 (H, W), H, W, cell_mm) of a GridMap, as the kernels take them."""
    occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
    return occ, int(occ.shape[0]), int(occ.shape[1]), float(gridmap.cell_size_m) * 1000.0

