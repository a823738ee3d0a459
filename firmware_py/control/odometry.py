"""Differential-drive dead reckoning from wheel encoder counts, in integers.

Owns the robot's pose estimate (world frame of `firmware_py.robot_spec`: x east,
y north, heading CCW from east) and the distance / relative bearing to a
goal. Everything is integer: positions in micrometres, angles in
microradians internally, millimetres and milliradians at the API. Sine,
cosine, atan2 and hypot come from a small CORDIC so the control path never
touches floats (the atan table below is a constant, computed once at import).
"""

from __future__ import annotations

import math

from firmware_py import robot_spec

# --- integer trigonometry (CORDIC) ------------------------------------------
PI_URAD = 3_141_593
TWO_PI_URAD = 6_283_185
HALF_PI_URAD = 1_570_796
_Q = 30  # fixed-point fraction bits of the CORDIC vectors
_ONE = 1 << _Q
_ITER = 26
# atan(2**-i) in nano-radians: one more decade than the µrad API so the sum
# of the table's rounding errors stays below a microradian.
_ATAN_NRAD = tuple(round(math.atan(2.0 ** -i) * 1e9) for i in range(_ITER))
_GAIN_INV_Q = round(_ONE * math.prod(1 / math.sqrt(1 + 4.0 ** -i) for i in range(_ITER)))


def wrap_urad(a: int) -> int:
    """Wrap an angle (µrad) into [-pi, pi)."""
    return (a + PI_URAD) % TWO_PI_URAD - PI_URAD


def wrap_mrad(a: int) -> int:
    """Wrap an angle (mrad) into [-pi, pi)."""
    return (a + 3142) % 6283 - 3142


def cos_sin_q30(angle_urad: int) -> tuple[int, int]:
    """(cos, sin) of an angle in µrad as Q30 integers (1.0 == 1 << 30)."""
    z = wrap_urad(angle_urad)
    flip = False
    # CORDIC converges for |z| <= ~1.74 rad: fold the rear half-plane forward.
    if z > HALF_PI_URAD:
        z -= PI_URAD
        flip = True
    elif z < -HALF_PI_URAD:
        z += PI_URAD
        flip = True
    z *= 1000  # nrad
    x, y = _GAIN_INV_Q, 0
    for i in range(_ITER):
        if z >= 0:
            x, y, z = x - (y >> i), y + (x >> i), z - _ATAN_NRAD[i]
        else:
            x, y, z = x + (y >> i), y - (x >> i), z + _ATAN_NRAD[i]
    return (-x, -y) if flip else (x, y)


def atan2_hypot(y: int, x: int) -> tuple[int, int]:
    """(atan2(y, x) in µrad within [-pi, pi), hypot(x, y)) for integers."""
    if x == 0 and y == 0:
        return 0, 0
    base = 0
    if x < 0:  # rotate by pi into the right half-plane
        x, y = -x, -y
        base = PI_URAD
    # Scale small vectors up so the shifts keep precision, then back.
    shift = max(0, _Q - max(abs(x), abs(y)).bit_length())
    x <<= shift
    y <<= shift
    z = 0
    for i in range(_ITER):
        if y > 0:
            x, y, z = x + (y >> i), y - (x >> i), z + _ATAN_NRAD[i]
        else:
            x, y, z = x - (y >> i), y + (x >> i), z - _ATAN_NRAD[i]
    angle = wrap_urad(base + (z + 500) // 1000)
    length = ((x * _GAIN_INV_Q) >> _Q) >> shift
    return angle, length


# --- odometry -----------------------------------------------------------------


def _round_div(n: int, d: int) -> int:
    """n / d rounded half away from zero, for a positive d."""
    return (n + d // 2) // d if n >= 0 else -((-n + d // 2) // d)


class Odometry:
    """Pose from cumulative left/right encoder counts (midpoint integration).

    The first `update` after construction or `reset` only records the counts.
    Counters are treated as `counter_bits`-bit two's complement and may wrap.
    """

    def __init__(self, x_mm: int = 0, y_mm: int = 0, heading_mrad: int = 0, *,
                 ticks_per_rev: int = robot_spec.ENCODER_TICKS_PER_REV,
                 wheel_radius_mm: int = robot_spec.WHEEL_RADIUS_MM,
                 wheel_base_mm: int = robot_spec.WHEEL_BASE_MM,
                 counter_bits: int = 32) -> None:
        if ticks_per_rev <= 0 or wheel_radius_mm <= 0 or wheel_base_mm <= 0:
            raise ValueError("ticks_per_rev, wheel_radius_mm and wheel_base_mm must be > 0")
        self.ticks_per_rev = ticks_per_rev
        self.wheel_base_um = wheel_base_mm * 1000
        self._circ_nm = robot_spec.wheel_circumference_nm(wheel_radius_mm)  # pi enters once, as a constant
        self._mod = 1 << counter_bits
        self._half = 1 << (counter_bits - 1)
        self.reset(x_mm, y_mm, heading_mrad)

    def reset(self, x_mm: int, y_mm: int, heading_mrad: int) -> None:
        """Set the pose; the next `update` re-references the counters."""
        self.x_um = int(x_mm) * 1000
        self.y_um = int(y_mm) * 1000
        self.heading_urad = wrap_urad(int(heading_mrad) * 1000)
        self._last: tuple[int, int] | None = None
        self._last_t_us: int | None = None
        self._rem = [0, 0]  # sub-nm remainders carried per wheel
        self.speed_mm_s = 0
        self.yaw_rate_mrad_s = 0
        self.distance_mm = 0  # path length travelled since reset (odometer)
        self._odo_nm = 0

    def deltas(self, left_ticks: int, right_ticks: int) -> tuple[int, int] | None:
        """Counter differences (wrap handled) since the last update; None before the first."""
        if self._last is None:
            return None
        return ((left_ticks - self._last[0] + self._half) % self._mod - self._half,
                (right_ticks - self._last[1] + self._half) % self._mod - self._half)

    def rebase(self, left_ticks: int, right_ticks: int, t_us: int | None = None) -> None:
        """Take these counts as the new reference without moving the pose
        (an implausible jump must not teleport the robot)."""
        self._last = (left_ticks, right_ticks)
        self._last_t_us = t_us

    def _ticks_to_nm(self, wheel: int, dticks: int) -> int:
        num = dticks * self._circ_nm + self._rem[wheel]
        q, self._rem[wheel] = divmod(num, self.ticks_per_rev)
        return q

    def update(self, left_ticks: int, right_ticks: int, t_us: int | None = None) -> None:
        """Integrate new cumulative counts (and estimate speed if `t_us` given)."""
        d = self.deltas(left_ticks, right_ticks)
        if d is None:
            self.rebase(left_ticks, right_ticks, t_us)
            return
        dl_t, dr_t = d
        self._last = (left_ticks, right_ticks)
        dl = self._ticks_to_nm(0, dl_t)
        dr = self._ticks_to_nm(1, dr_t)
        ds_nm = (dl + dr) // 2
        # dtheta [µrad] = (dr - dl) [nm] / base [nm] * 1e6 = (dr - dl) * 1e3 / base [µm]
        dth = _round_div((dr - dl) * 1000, self.wheel_base_um)
        mid = self.heading_urad + dth // 2
        c, s = cos_sin_q30(mid)
        self.x_um += _round_div(ds_nm * c, 1000 << _Q)
        self.y_um += _round_div(ds_nm * s, 1000 << _Q)
        self.heading_urad = wrap_urad(self.heading_urad + dth)
        self._odo_nm += abs(ds_nm)
        self.distance_mm = self._odo_nm // 1_000_000
        if t_us is not None and self._last_t_us is not None and t_us > self._last_t_us:
            dt = t_us - self._last_t_us
            self.speed_mm_s = _round_div(ds_nm * 1000, dt * 1000)
            self.yaw_rate_mrad_s = _round_div(dth * 1000, dt)
        self._last_t_us = t_us

    @property
    def x_mm(self) -> int:
        return _round_div(self.x_um, 1000)

    @property
    def y_mm(self) -> int:
        return _round_div(self.y_um, 1000)

    @property
    def heading_mrad(self) -> int:
        return wrap_mrad(_round_div(self.heading_urad, 1000))

    def pose_mm(self) -> tuple[int, int, int]:
        """(x_mm, y_mm, heading_mrad)."""
        return self.x_mm, self.y_mm, self.heading_mrad

    def goal_vector(self, gx_mm: int, gy_mm: int) -> tuple[int, int]:
        """(distance_mm, bearing_mrad) to a goal; bearing relative to the
        heading, CCW positive, in [-pi, pi)."""
        ang, dist_um = atan2_hypot(gy_mm * 1000 - self.y_um, gx_mm * 1000 - self.x_um)
        rel = wrap_urad(ang - self.heading_urad)
        return _round_div(dist_um, 1000), wrap_mrad(_round_div(rel, 1000))
