"""The pymunk world and sensors: walls hold, rays match geometry, encoders and bumper."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from firmware_py import robot_spec
from sim_bridge.plant import Plant, SimConfig
from sim_bridge.sensors import RangeParams, RangeSensors, WheelEncoders, bumper_signals
from sim_bridge.world import Pose, World

R = robot_spec.ROBOT_RADIUS_MM / 1000
DT = robot_spec.PHYSICS_DT_US / 1e6
VMAX = robot_spec.MAX_WHEEL_SPEED_MM_S / 1000


def _drive(world: World, left: float, right: float, seconds: float) -> list[Pose]:
    poses = []
    for _ in range(round(seconds / DT)):
        world.drive(left, right)
        world.step(DT)
        poses.append(world.pose)
    return poses


def test_robot_cannot_pass_a_one_cell_wall_at_maximum_speed():
    occ = np.zeros((6, 10), bool)
    occ[:, 5] = True  # a 0.5 m thick wall from x=2.5 to x=3.0 across the whole arena
    world = World(occ, 0.5, Pose(1.0, 1.5, 0.0))
    poses = _drive(world, VMAX, VMAX, 10.0)
    assert max(p.x for p in poses) <= 2.5 - R + 0.002  # slop is 0.5 mm
    assert world.pose.x > 2.5 - R - 0.002  # it did reach the wall
    # and diagonally into a corner, spinning on the way: still inside
    world = World(occ, 0.5, Pose(1.0, 1.0, math.radians(30)))
    poses = _drive(world, VMAX, VMAX * 0.9, 20.0)
    tol = 0.005  # transient contact overlap at full speed, far from tunnelling (wall: 0.5 m)
    assert all(R - tol <= p.x <= 2.5 - R + tol and R - tol <= p.y <= 3.0 - R + tol for p in poses)


def test_robot_stays_inside_outer_walls_with_heavy_traction():
    from sim_bridge.world import BodyParams
    world = World(np.zeros((4, 4), bool), 0.5, Pose(1.0, 1.0, math.radians(45)),
                  BodyParams(traction_accel_m_s2=1000.0))
    poses = _drive(world, VMAX, VMAX, 10.0)
    assert all(p.x <= 2.0 - R + 0.003 and p.y <= 2.0 - R + 0.003 for p in poses)


def test_start_pose_is_checked():
    occ = np.zeros((4, 4), bool)
    occ[1, 1] = True
    with pytest.raises(ValueError, match="overlaps an obstacle"):
        World(occ, 0.5, Pose(0.75, 1.25, 0.0))
    with pytest.raises(ValueError, match="outside"):
        World(occ, 0.5, Pose(0.05, 1.0, 0.0))


def test_ray_distances_match_hand_computed_geometry():
    # 8 x 8 cells of 0.5 m (4 x 4 m). One obstacle cell at (col 5, row 3):
    # x 2.5..3.0, y 2.0..2.5. Robot at (1.25, 2.25) facing east.
    occ = np.zeros((8, 8), bool)
    occ[3, 5] = True
    world = World(occ, 0.5, Pose(1.25, 2.25, 0.0))
    sensors = RangeSensors(world, RangeParams(fan_rays=1, noise_std_mm=0.0), random.Random(0))
    got = sensors.true_ranges_mm()
    r_mm = R * 1000
    diag = math.sqrt(2)
    expected = [
        1250 - r_mm,  # 0: east to the obstacle's west face at x = 2.5
        None,  # 45 deg: north wall at 1.75 * sqrt2 = 2.47 m from the centre, out of reach
        1750 - r_mm,  # 90 deg: north wall y = 4
        1250 * diag - r_mm,  # 135 deg: west wall x = 0 (1.25 m away) before the north wall
        1250 - r_mm,  # 180 deg: west wall
        1250 * diag - r_mm,  # -135 deg: west wall (south wall is 2.25 m away)
        None,  # -90 deg: south wall 2.25 m from the centre = 2.1 m from the rim > RANGE_MAX
        None,  # -45 deg: the obstacle is north-east; walls too far
    ]
    for i, (g, e) in enumerate(zip(got, expected, strict=True)):
        if e is None:
            assert g is None, f"sensor {i}: {g}"
        else:
            assert g == pytest.approx(e, abs=0.5), f"sensor {i}"
    # rotate the robot by 90 deg: sensor 0 now looks north, sensor 6 looks east
    world.body.angle = math.pi / 2
    got = sensors.true_ranges_mm()
    assert got[0] == pytest.approx(1750 - r_mm, abs=0.5)
    assert got[6] == pytest.approx(1250 - r_mm, abs=0.5)
    assert got[2] == pytest.approx(1250 - r_mm, abs=0.5)  # now looking west
    assert got[4] is None  # now looking south: 2.1 m from the rim
    # the readings on the bus: exact, valid, and too far where nothing is in reach
    world.body.angle = 0.0
    readings = sensors.read()
    assert readings[0] == (round(1250 - r_mm), robot_spec.RANGE_VALID)
    assert readings[1] == (robot_spec.RANGE_MAX_MM, robot_spec.RANGE_TOO_FAR)
    assert readings[6] == (robot_spec.RANGE_MAX_MM, robot_spec.RANGE_TOO_FAR)  # 2100 mm > RANGE_MAX


def test_fan_reports_the_nearest_ray_of_the_cone():
    occ = np.zeros((8, 8), bool)
    world = World(occ, 0.5, Pose(3.0, 1.0, math.pi / 2))  # facing north, east wall 1 m away
    fan = RangeSensors(world, RangeParams(fan_rays=3, noise_std_mm=0.0), random.Random(0))
    one = RangeSensors(world, RangeParams(fan_rays=1, noise_std_mm=0.0), random.Random(0))
    # sensor 7 looks 45 deg right of the heading: world 45 deg. Its fan's right edge ray
    # (45 deg - FOV/2) meets the east wall first.
    centre = math.pi / 2 + robot_spec.SENSOR_ANGLES_MRAD[7] / 1000  # ~45 deg (angles are whole mrad)
    edge = centre - robot_spec.SENSOR_FOV_MRAD / 2000
    assert fan.true_ranges_mm()[7] == pytest.approx(1000 / math.cos(edge) - R * 1000, abs=0.5)
    assert one.true_ranges_mm()[7] == pytest.approx(1000 / math.cos(centre) - R * 1000, abs=0.5)


def test_too_close_dropout_and_seeded_noise():
    occ = np.zeros((4, 4), bool)
    world = World(occ, 0.5, Pose(R + 0.010, 1.0, 0.0))  # rim 10 mm from the west wall
    quiet = RangeSensors(world, RangeParams(fan_rays=1, noise_std_mm=0.0), random.Random(0))
    assert quiet.read()[4] == (robot_spec.RANGE_MIN_MM, robot_spec.RANGE_TOO_CLOSE)
    dead = RangeSensors(world, RangeParams(dropout=1.0), random.Random(0))
    assert dead.read() == [(0, robot_spec.RANGE_INVALID)] * robot_spec.SENSOR_COUNT

    def readings(seed):
        s = RangeSensors(world, RangeParams(noise_std_mm=30.0, dropout=0.2), random.Random(seed))
        return [s.read() for _ in range(20)]

    assert readings(1) == readings(1)
    assert readings(1) != readings(2)
    flat = [r for rs in readings(3) for r in rs]
    assert any(st == robot_spec.RANGE_INVALID for _, st in flat)
    assert any(st == robot_spec.RANGE_VALID for _, st in flat)


def test_encoders_count_ground_travel_and_slip_is_seeded():
    world = World(np.zeros((4, 8), bool), 0.5, Pose(0.5, 1.0, 0.0))
    enc = WheelEncoders(world, random.Random(0))
    for _ in range(round(2.0 / DT)):
        world.drive(0.5, 0.5)
        enc.integrate(DT)  # the plant's order: pymunk moves the body by its pre-step velocity
        world.step(DT)
    travelled = world.pose.x - 0.5
    per_m = robot_spec.ENCODER_TICKS_PER_REV / (2 * math.pi * robot_spec.WHEEL_RADIUS_MM / 1000)
    left, right = enc.counts()
    assert travelled > 0.9
    assert left == pytest.approx(travelled * per_m, abs=3) and right == pytest.approx(left, abs=1)

    def slipped(seed):
        w = World(np.zeros((4, 8), bool), 0.5, Pose(0.5, 1.0, 0.0))
        e = WheelEncoders(w, random.Random(seed), slip_std=0.05)
        for _ in range(200):
            w.drive(0.5, 0.5)
            e.integrate(DT)
            w.step(DT)
        return e.counts()

    assert slipped(4) == slipped(4) and slipped(4) != slipped(5)


def test_bumper_reports_contact_zone_and_events():
    occ = np.zeros((4, 8), bool)
    occ[:, 4] = True  # wall at x = 2.0
    plant = Plant(occ, SimConfig(), Pose(1.0, 1.0, 0.0))
    assert bumper_signals(plant.world)["Bump_Pressed"] == 0
    _drive(plant.world, VMAX, VMAX, 3.0)
    sig = bumper_signals(plant.world)
    assert sig["Bump_Pressed"] == 1 and sig["Bump_Front"] == 1
    assert sig["Bump_Left"] == sig["Bump_Right"] == sig["Bump_Rear"] == 0
    assert sig["Bump_Events"] >= 1 and abs(sig["Bump_AngleMrad"]) < 50
    _drive(plant.world, -VMAX, -VMAX, 1.0)
    assert bumper_signals(plant.world)["Bump_Pressed"] == 0
