"""Kinematic twin: geometry against hand-computed values, and the jitted
encoder against the reference `firmware_py.kinds.sector.encoder.SectorEncoder`."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_py import robot_spec
from firmware_py.kinds.sector import encoder as sector_encoder
from firmware_py.kinds.sector.encoder import SectorEncoder, bearing_sector
from ground_station.learn.sector import twin as T

CELL = 500.0


def _occ(rows: list[str]) -> np.ndarray:
    return np.array([[ch == "@" for ch in r] for r in rows], dtype=np.uint8)


# --- fast encoder == reference --------------------------------------------------

_encoders = st.builds(
    SectorEncoder,
    bearing_sectors=st.integers(1, 32),
    sensors=st.lists(st.integers(0, robot_spec.SENSOR_COUNT - 1), min_size=1, max_size=robot_spec.SENSOR_COUNT,
                     unique=True).map(tuple),
    range_edges_mm=st.lists(st.integers(0, 4000), min_size=0, max_size=5, unique=True).map(
        lambda v: tuple(sorted(v))),
)
_ranges = st.lists(st.integers(0, 5000), min_size=robot_spec.SENSOR_COUNT, max_size=robot_spec.SENSOR_COUNT)
_status = st.lists(st.sampled_from([robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_CLOSE, robot_spec.RANGE_TOO_FAR,
                                    robot_spec.RANGE_INVALID]),
                   min_size=robot_spec.SENSOR_COUNT, max_size=robot_spec.SENSOR_COUNT)


@settings(max_examples=2000, deadline=None)
@given(enc=_encoders, bearing=st.integers(-100_000, 100_000), ranges=_ranges, status=_status)
def test_fast_encoder_equals_reference(enc, bearing, ranges, status):
    sectors, sensors, edges, _ = T.encoder_arrays(enc)
    fast = T.encode_fast(bearing, np.array(ranges, dtype=np.int64), np.array(status, dtype=np.int64),
                         sectors, sensors, edges)
    assert fast == enc.encode(bearing, ranges, status)
    assert 0 <= fast < enc.n_states


@settings(max_examples=2000, deadline=None)
@given(bearing=st.integers(-10**9, 10**9), sectors=st.integers(1, 64))
def test_fast_bearing_sector_equals_reference(bearing, sectors):
    assert T.bearing_sector_fast(bearing, sectors) == bearing_sector(bearing, sectors)


def test_constants_follow_the_contract():
    assert T.TWO_PI_MRAD == sector_encoder.TWO_PI_MRAD
    from ground_station.learn.sector import kernels as K
    assert robot_spec.ACTION_NAMES[K.REVERSE] == "reverse"
    assert T.N_SUBSTEPS * robot_spec.PHYSICS_DT_US == robot_spec.CONTROL_PERIOD_US


# --- geometry -------------------------------------------------------------------

def test_cell_world_conventions_match_robot_helpers():
    h = 7
    for col, row in [(0, 0), (3, 6), (6, 2)]:
        x, y = T.cell_centre(col, row, h, CELL)
        assert (x, y) == robot_spec.cell_center_mm(col, row, h, int(CELL))
        assert T.cell_of(x, y, h, CELL) == (col, row) == robot_spec.world_to_cell(int(x), int(y), h, int(CELL))


def test_disc_collision_against_cells_and_border():
    occ = _occ(["...",
                ".@.",
                "..."])
    h, w = occ.shape
    # centre of the obstacle cell is (750, 750); its west face is x = 500
    assert T.disc_hits(occ, h, w, CELL, 500 - 149.0, 750.0, 150.0)
    assert not T.disc_hits(occ, h, w, CELL, 500 - 151.0, 750.0, 150.0)
    # corner (500, 1000): diagonal distance
    d = 150.0 / math.sqrt(2)
    assert T.disc_hits(occ, h, w, CELL, 500 - d + 1, 1000 + d - 1, 150.0)
    assert not T.disc_hits(occ, h, w, CELL, 500 - d - 1, 1000 + d + 1, 150.0)
    # border
    assert T.disc_hits(occ, h, w, CELL, 149.0, 250.0, 150.0)
    assert not T.disc_hits(occ, h, w, CELL, 151.0, 250.0, 150.0)
    assert T.disc_hits(occ, h, w, CELL, 250.0, 1500 - 149.0, 150.0)


def test_motion_matches_the_wheel_speed_table():
    occ = _occ(["....", "....", "....", "...."])
    h, w = occ.shape
    period = robot_spec.CONTROL_PERIOD_US / 1e6
    for a, (vl, vr) in enumerate(robot_spec.ACTION_WHEEL_SPEEDS_MM_S):
        th0 = 0.3
        x, y, th, driven, hit = T.move(occ, h, w, CELL, 1000.0, 1000.0, th0, a, T.DEFAULT_TW)
        v = (vl + vr) / 2
        om = (vr - vl) / robot_spec.WHEEL_BASE_MM
        assert not hit
        assert math.isclose(driven, abs(v) * period)
        assert math.isclose(T.wrap_angle(th - th0 - om * period), 0.0, abs_tol=1e-12)
        if om == 0:
            assert math.isclose(x, 1000 + v * period * math.cos(th0))
            assert math.isclose(y, 1000 + v * period * math.sin(th0))
        else:  # exact arc: chord length 2 (v/om) sin(om T / 2)
            chord = abs(2 * v / om * math.sin(om * period / 2))
            assert math.isclose(math.hypot(x - 1000, y - 1000), chord, abs_tol=1e-9)


def test_driving_into_a_wall_is_a_collision_at_contact():
    occ = _occ(["....",
                "...@",
                "...."])
    h, w = occ.shape
    x, y, th = 1250.0, 750.0, 0.0  # cell (2, 1), facing the obstacle at (3, 1)
    hit = False
    for _ in range(100):
        x, y, th, _, hit = T.move(occ, h, w, CELL, x, y, th, 0, T.DEFAULT_TW)
        if hit:
            break
    assert hit
    # stops within one substep of touching x = 1500 - radius
    contact = 1500 - robot_spec.ROBOT_RADIUS_MM
    assert contact <= x <= contact + 400 * robot_spec.PHYSICS_DT_US / 1e6 + 1e-9


def test_range_rays_match_hand_geometry():
    occ = _occ(["......",
                "......",
                ".....@",
                "......"])
    h, w = occ.shape
    x, y = 750.0, 750.0  # centre of cell (1, 2)
    # straight ray east from the centre hits x = 2500 (cell (5, 2))
    assert math.isclose(T.ray_cast(occ, h, w, CELL, x, y, 0.0, 5000.0), 1750.0)
    # north to the border y = 2000
    assert math.isclose(T.ray_cast(occ, h, w, CELL, x, y, math.pi / 2, 5000.0), 1250.0)
    # 45 deg: the border x = 3000 or y = 2000 first -> y: 1250 * sqrt 2
    assert math.isclose(T.ray_cast(occ, h, w, CELL, x, y, math.pi / 4, 5000.0), 1250 * math.sqrt(2))
    assert T.ray_cast(occ, h, w, CELL, x, y, 0.0, 1000.0) == 1000.0
    # sensor 0 (front) facing east: rim at x = 900; fan of rays +-FOV/2 -> the
    # nearest of the centre ray (1600) and the edge rays (border / wall)
    rng, status = T.sense_one(occ, h, w, CELL, x, y, 0.0, 0, T.DEFAULT_TW)
    half = robot_spec.SENSOR_FOV_MRAD / 2000
    ox = x + robot_spec.SENSOR_MOUNT_RADIUS_MM
    edge_south = 750.0 / math.sin(half)  # to the border y = 0
    expect = min(2500 - ox, edge_south) if robot_spec.SENSOR_FAN_RAYS > 1 else 2500 - ox
    assert status == robot_spec.RANGE_VALID and rng == round(expect)
    # back sensor (index 4) facing west: rim at x = 600, border at 0 -> 600
    rng, status = T.sense_one(occ, h, w, CELL, x, y, 0.0, 4, T.DEFAULT_TW)
    assert (rng, status) == (600, robot_spec.RANGE_VALID)
    # close to the border: too close; open view: too far
    rng, status = T.sense_one(occ, h, w, CELL, 160.0, 750.0, math.pi, 0, T.DEFAULT_TW)
    assert (rng, status) == (robot_spec.RANGE_MIN_MM, robot_spec.RANGE_TOO_CLOSE)
    big = np.zeros((20, 20), dtype=np.uint8)
    rng, status = T.sense_one(big, 20, 20, CELL, 5000.0, 5000.0, 0.0, 0, T.DEFAULT_TW)
    assert (rng, status) == (robot_spec.RANGE_MAX_MM, robot_spec.RANGE_TOO_FAR)


def test_sense_equals_sense_one_everywhere():
    rng = np.random.default_rng(3)
    occ = (rng.random((8, 9)) < 0.25).astype(np.uint8)
    h, w = occ.shape
    which = np.ones(robot_spec.SENSOR_COUNT, dtype=np.bool_)
    ranges = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
    status = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
    n = 0
    while n < 300:
        x, y = rng.uniform(0, w * CELL), rng.uniform(0, h * CELL)
        if T.disc_hits(occ, h, w, CELL, x, y, float(robot_spec.ROBOT_RADIUS_MM)):
            continue
        th = rng.uniform(-math.pi, math.pi)
        T.sense(occ, h, w, CELL, x, y, th, which, ranges, status, T.DEFAULT_TW)
        for i in range(robot_spec.SENSOR_COUNT):
            r1, s1 = T.sense_one(occ, h, w, CELL, x, y, th, i, T.DEFAULT_TW)
            assert abs(r1 - ranges[i]) <= 1 and s1 == status[i]
        n += 1


def test_bearing_and_potential():
    # goal straight north of a robot facing east: +90 deg
    assert T.bearing_mrad(0.0, 0.0, 0.0, 0.0, 100.0) == 1571
    assert T.bearing_mrad(0.0, 0.0, math.pi / 2, 100.0, 0.0) == -1571
    from ground_station.maps import octile_distances
    occ = _occ(["....",
                ".@@.",
                "...."])
    h, w = occ.shape
    d = octile_distances(occ.astype(bool), 0, 2)  # goal cell (0, 2), south-west
    gx, gy = T.cell_centre(0, 2, h, CELL)
    # next to the goal it is the Euclidean distance
    assert math.isclose(T.potential(d, occ, h, w, CELL, gx + 100, gy + 50), math.hypot(100, 50))
    # at a cell centre it is the octile distance
    cx, cy = T.cell_centre(3, 0, h, CELL)
    assert math.isclose(T.potential(d, occ, h, w, CELL, cx, cy), d[0, 3] * CELL)
