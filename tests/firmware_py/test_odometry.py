"""Integer odometry and CORDIC trig against float references and hand-checked poses."""

import math
import random

import pytest

from firmware_py import robot_spec
from firmware_py.control.odometry import Odometry, atan2_hypot, cos_sin_q30, wrap_mrad, wrap_urad

TICKS_PER_MM = robot_spec.ENCODER_TICKS_PER_REV / (2 * math.pi * robot_spec.WHEEL_RADIUS_MM)


def ticks(mm: float) -> int:
    return round(mm * TICKS_PER_MM)


def test_cordic_sin_cos_match_math_within_two_microradians():
    rng = random.Random(1)
    for _ in range(3000):
        a = rng.randint(-20_000_000, 20_000_000)
        c, s = cos_sin_q30(a)
        assert abs(c / 2**30 - math.cos(a / 1e6)) < 2e-6
        assert abs(s / 2**30 - math.sin(a / 1e6)) < 2e-6


def test_cordic_atan2_and_hypot_match_math():
    rng = random.Random(2)
    for _ in range(3000):
        x, y = rng.randint(-10**7, 10**7), rng.randint(-10**7, 10**7)
        ang, length = atan2_hypot(y, x)
        err = (ang / 1e6 - math.atan2(y, x) + math.pi) % (2 * math.pi) - math.pi
        assert abs(err) < 2e-6
        assert abs(length - math.hypot(x, y)) <= 1 + 2e-5 * math.hypot(x, y)
    assert atan2_hypot(0, 0) == (0, 0)
    assert atan2_hypot(3, 4)[1] == 5
    assert atan2_hypot(1000, 0)[0] == 1_570_796


def test_wraps():
    assert wrap_mrad(100) == 100 and wrap_mrad(-100) == -100
    assert wrap_mrad(3200) == 3200 - 6283
    assert wrap_mrad(-3200) == -3200 + 6283
    assert all(-3142 <= wrap_mrad(a) < 3142 for a in range(-20000, 20000, 7))
    assert wrap_urad(0) == 0
    assert -3_141_593 <= wrap_urad(10**9) < 3_141_593


def test_straight_line_one_revolution():
    o = Odometry(1000, 2000, 1571)  # facing north
    o.update(0, 0, 0)
    n = robot_spec.ENCODER_TICKS_PER_REV
    o.update(n, n, 500_000)
    circ = 2 * math.pi * robot_spec.WHEEL_RADIUS_MM
    assert o.x_mm == 1000
    assert o.y_mm == round(2000 + circ)
    assert o.heading_mrad == 1571
    assert o.speed_mm_s == round(circ / 0.5)
    assert o.distance_mm == int(circ)


def test_spin_in_place_half_turn_and_back():
    o = Odometry(0, 0, 0)
    o.update(0, 0)
    half = ticks(math.pi * robot_spec.WHEEL_BASE_MM / 2)  # each wheel's arc for a half turn
    o.update(-half, half)
    assert abs(wrap_mrad(o.heading_mrad - 3142)) <= 2
    assert (o.x_mm, o.y_mm) == (0, 0)
    o.update(0, 0)
    assert o.heading_mrad == 0


def test_circle_in_small_steps_returns_to_start():
    # Left wheel on a 500 mm radius circle, right wheel outside: full circle CCW.
    r = 500
    o = Odometry(0, 0, 0)
    o.update(0, 0)
    steps = 400
    inner = 2 * math.pi * (r - robot_spec.WHEEL_BASE_MM / 2)
    outer = 2 * math.pi * (r + robot_spec.WHEEL_BASE_MM / 2)
    for k in range(1, steps + 1):
        o.update(ticks(inner * k / steps), ticks(outer * k / steps))
        if k == steps // 4:  # a quarter circle CCW from heading east: at (r, r), facing north
            assert abs(o.x_mm - r) <= 3 and abs(o.y_mm - r) <= 3
            assert abs(o.heading_mrad - 1571) <= 3
    assert abs(o.x_mm) <= 3 and abs(o.y_mm) <= 3
    assert abs(wrap_mrad(o.heading_mrad)) <= 3


def test_counter_wrap_is_a_small_step():
    o = Odometry(0, 0, 0)
    o.update(2**31 - 10, 2**31 - 10)
    o.update(-(2**31) + 90, -(2**31) + 90)  # +100 ticks through the int32 wrap
    assert o.x_mm == round(100 / TICKS_PER_MM)


def test_goal_vector_distance_and_relative_bearing():
    o = Odometry(1000, 1000, 3142)  # facing west
    dist, bearing = o.goal_vector(1000, 2000)  # due north: 90 deg to the right of west
    assert dist == 1000
    assert abs(bearing - (-1571)) <= 1
    dist, bearing = o.goal_vector(0, 1000)  # straight ahead
    assert dist == 1000 and abs(bearing) <= 1


def test_bad_geometry_rejected():
    with pytest.raises(ValueError):
        Odometry(ticks_per_rev=0)
