"""The collision monitor (firmware_py.control.collision): the straight part of any command toward a
read point in the robot's path is slowed, then removed; turning is left alone; points beside the
swept corridor (a corridor's walls) do not count; and the controller applies it to whatever it sends
(here the exploration wander and Manual driving, besides every policy kind)."""

from __future__ import annotations

import pytest

from firmware_py import robot_spec
from firmware_py.control.collision import FAR_MM, limit, travel_gap_mm

N = robot_spec.SENSOR_COUNT
V, FAR, CLOSE, BAD = (robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_FAR, robot_spec.RANGE_TOO_CLOSE,
                      robot_spec.RANGE_INVALID)
ANGLE = {a: i for i, a in enumerate(robot_spec.SENSOR_ANGLES_MRAD)}


def _reading(at_mrad: int, mm: int, status: int = V) -> tuple[list[int], list[int]]:
    ranges, st = [2000] * N, [FAR] * N
    ranges[ANGLE[at_mrad]], st[ANGLE[at_mrad]] = mm, status
    return ranges, st


def test_the_gap_ahead_is_the_front_reading_and_nothing_behind_or_beside_counts():
    assert travel_gap_mm(*_reading(0, 300), reverse=False) == 300  # sensors sit on the robot's rim
    assert travel_gap_mm(*_reading(0, 300), reverse=True) == FAR_MM  # not in the way backwards
    rear = robot_spec.SENSOR_ANGLES_MRAD[N // 2]
    assert travel_gap_mm(*_reading(rear, 120), reverse=True) == 120
    side = [a for a in robot_spec.SENSOR_ANGLES_MRAD if abs(a - 1571) < 10][0]  # +90 deg
    assert travel_gap_mm(*_reading(side, 60), reverse=False) == FAR_MM  # beside the corridor
    # under CONTACT_MM it may be a body touching the rim in the blind gap ahead of (or behind) the
    # side cone: both ways are held (tests/ground_station/test_monitor_contact.py)
    assert travel_gap_mm(*_reading(side, 30), reverse=False) == 0
    assert travel_gap_mm(*_reading(side, 30), reverse=True) == 0
    diag = [a for a in robot_spec.SENSOR_ANGLES_MRAD if abs(a - 785) < 10][0]  # +45 deg
    assert travel_gap_mm(*_reading(diag, 400), reverse=False) == FAR_MM  # a corridor wall on the diagonal
    near_diag = travel_gap_mm(*_reading(diag, 30), reverse=False)
    assert 0 <= near_diag < 100  # close in on the diagonal: the rim will touch it soon
    assert travel_gap_mm(*_reading(0, 300, BAD), reverse=False) == FAR_MM  # invalid readings say nothing
    assert travel_gap_mm(*_reading(0, 999, CLOSE), reverse=False) == 0  # under the minimum: the worst


@pytest.mark.parametrize("front, want, what", [(1500, (300, 300), ""), (150, (150, 150), "slow"),
                                               (30, (0, 0), "stop")])
def test_straight_motion_is_slowed_then_stopped(front, want, what):
    assert limit(300, 300, *_reading(0, front), stop_mm=50, slow_mm=200, slow_pct=50) == (*want, what)


def test_turning_in_place_is_left_alone_and_an_arc_keeps_its_turn():
    r, s = _reading(0, 10)
    assert limit(-200, 200, r, s, 50, 200, 50) == (-200, 200, "")  # in place: touches nothing
    assert limit(100, 300, r, s, 50, 200, 50) == (-100, 100, "stop")  # the straight 200 goes, the turn stays
    assert limit(-300, -300, r, s, 50, 200, 50) == (-300, -300, "")  # backing away from it
    assert limit(300, 300, r, s, 0, 0, 50) == (300, 300, "")  # both zones off


def test_the_controller_limits_what_it_sends_in_manual_mode():
    from firmware_py.control.controller import Controller
    from firmware_py.control.io import Inputs
    from firmware_py.vehicle import Mode

    ctrl = Controller()
    t = 0

    def tick(front: int):
        nonlocal t
        t += robot_spec.CONTROL_PERIOD_US
        ranges, status = _reading(0, front)
        return ctrl.step(Inputs(ranges_mm=ranges, range_status=status, ranges_us=[t, t], enc_left=0, enc_right=0,
                                enc_us=t, bumper_us=t, driver_us=t), t)

    tick(2000)
    assert ctrl.arm() == (True, "") and ctrl.set_mode(Mode.MANUAL)[0]
    ctrl.manual_control(1000, 0, t)  # full ahead
    out = tick(2000)
    assert out.motor is not None and out.motor.left_mm_s == out.motor.right_mm_s > 0
    ctrl.manual_control(1000, 0, t)
    out = tick(30)  # a reading 30 mm ahead
    assert out.motor is not None and (out.motor.left_mm_s, out.motor.right_mm_s) == (0, 0)
    assert ctrl.collision_ticks["stop"] == 1


def test_the_controller_fills_no_blind_gap_for_a_reading_its_map_explains():
    """A reading under CONTACT_MM beside the robot holds a step ahead (a body may touch the rim in the
    blind gap ahead of that cone: tests/ground_station/test_monitor_contact.py), unless the robot's map
    explains it at the pose: a block's face 30 mm off the left flank, driven along in Manual."""
    from firmware_py.control.controller import Controller
    from firmware_py.control.io import Inputs, Outputs
    from firmware_py.mapdata import grid_from_rows
    from firmware_py.vehicle import Mode

    def ahead_after(with_map: bool) -> tuple[int, int]:
        ctrl = Controller()
        if with_map:  # 500 mm cells, row 0 north: a block row at y 1000..1500, the robot below it
            assert ctrl.set_robot_map(grid_from_rows(["." * 6] * 3 + ["@" * 6] + ["." * 6] * 2, 500))[0]
        pose = (1250, 1000 - robot_spec.ROBOT_RADIUS_MM - 30, 0)  # facing east along the face
        ctrl.odom.reset(*pose)
        if ctrl.loc is not None:  # with its map (and no policy) the robot localises on it
            ctrl.loc.init_pose(*pose)
        left = [a for a in robot_spec.SENSOR_ANGLES_MRAD if abs(a - 1571) < 10][0]
        ranges, status = _reading(left, 30)
        t = 0

        def tick() -> Outputs:
            nonlocal t
            t += robot_spec.CONTROL_PERIOD_US
            return ctrl.step(Inputs(ranges_mm=ranges, range_status=status, ranges_us=[t, t], enc_left=0,
                                    enc_right=0, enc_us=t, bumper_us=t, driver_us=t), t)

        tick()
        assert ctrl.arm() == (True, "") and ctrl.set_mode(Mode.MANUAL)[0]
        ctrl.manual_control(1000, 0, t)  # full ahead
        out = tick()
        assert out.motor is not None
        return out.motor.left_mm_s, out.motor.right_mm_s

    assert ahead_after(with_map=False) == (0, 0)
    moving = ahead_after(with_map=True)
    assert moving[0] == moving[1] > 0


def test_a_sector_memory_step_the_monitor_holds_is_walled_and_the_robot_goes_back():
    """The Bug kind's cell step held by the collision monitor for STEP_BLOCKED_US: back to the cell it
    left, and that move reads as a wall there (for WALLED_US), so the Bug decides another way round."""
    from firmware_py.kinds import sector_memory as sm
    from firmware_py.kinds.base import DriveTick
    from firmware_py.kinds.sector_memory.gridbug import DIR_HEADING_MRAD
    from firmware_py.kinds.stepper import STEP_BLOCKED_US, Step
    from firmware_py.policy import load_policy
    from firmware_py.shipped_policies import shipped_policy

    driver = sm.SectorMemoryDriver(load_policy(shipped_policy("sector_memory")))
    c = driver.policy.encoder.cell_mm
    east = DIR_HEADING_MRAD.index(0)  # the grid direction facing east (heading 0)
    driver.open = Step((3 * c + c // 2, 2 * c + c // 2), 0, turning=False)  # east, from cell (2, 2)

    def tick(now_us: int, blocked_us: int, x: int) -> DriveTick:
        return DriveTick(now_us=now_us, goal=(9 * c, 2 * c + c // 2), goal_index=0, drive_key=((0, 0), 0),
                         pose_mm=(x, 2 * c + c // 2, 0), goal_bearing_mrad=0, ranges_mm=[2000] * N,
                         range_status=[FAR] * N, goal_vector=lambda px, py: (abs(px - x), 0 if px >= x else 3142),
                         blocked_us=blocked_us)

    driver._key = ((0, 0), 0)
    driver.step(tick(1_000_000, STEP_BLOCKED_US - 1, 2 * c + 300))
    assert driver.open.target == (3 * c + c // 2, 2 * c + c // 2)  # not yet: still waiting
    driver.step(tick(2_000_000, STEP_BLOCKED_US, 2 * c + 300))
    assert driver.open.target == (2 * c + c // 2, 2 * c + c // 2) and driver.open.heading_mrad == 3142  # back west
    ranges, status = driver._with_walled(tick(2_000_000, 0, 2 * c + c // 2), 2, 2, east)
    assert (ranges[0], status[0]) == (robot_spec.RANGE_MIN_MM, V)  # the east move reads as a wall ...
    assert driver._with_walled(tick(2_000_000 + sm.WALLED_US, 0, 0), 2, 2, east)[1][0] == FAR  # ... for a while


def test_remembered_obstacle_points_cover_the_gaps_between_the_sensor_cones():
    """A point the kind remembers, in the robot's path but seen by no sensor now (between two cones),
    still stops the straight motion; one beside the swept corridor does not."""
    from firmware_py.control.collision import robot_frame

    nothing = ([2000] * N, [FAR] * N)
    pose = (1000, 1000, 1571)  # facing north
    ahead = robot_frame([(1100, 1190)], pose)  # 190 mm ahead, 100 mm to the right (within the radius)
    assert abs(ahead[0][0] - 190) < 1 and abs(ahead[0][1] + 100) < 1
    assert limit(300, 300, *nothing, 50, 200, 50, ahead) == (150, 150, "slow")  # rim to point 78 mm
    close = robot_frame([(1100, 1140)], pose)  # 28 mm from the rim
    assert limit(300, 300, *nothing, 50, 200, 50, close) == (0, 0, "stop")
    beside = robot_frame([(1200, 1150)], pose)  # 200 mm to the right: beside the swept corridor
    assert limit(300, 300, *nothing, 50, 200, 50, beside) == (300, 300, "")
    assert limit(-300, -300, *nothing, 50, 200, 50, close) == (-300, -300, "")  # backing away


def test_the_gap_along_an_arc_matches_driving_the_arc_in_half_millimetre_steps():
    """`path_gap_mm` on a turning command: the first contact of the rim with a point, checked against
    integrating the unicycle model, for forward, backward, left and right arcs."""
    import math
    import random

    from firmware_py.control.collision import path_gap_mm

    rng = random.Random(1)
    radius, base = robot_spec.ROBOT_RADIUS_MM, robot_spec.WHEEL_BASE_MM
    checked = turning_hits = 0
    while checked < 400:
        left, right = rng.randint(-400, 400), rng.randint(-400, 400)
        point = (rng.uniform(-500, 500), rng.uniform(-500, 500))
        if left + right == 0 or math.hypot(*point) <= radius:
            continue
        x = y = th = s = 0.0
        v, w = (left + right) / 2, (right - left) / base
        dt, want = 0.5 / abs(v), FAR_MM
        while s < 1000 and abs(th) <= math.pi:
            if math.hypot(point[0] - x, point[1] - y) < radius:
                want = int(s)
                break
            x, y, th, s = x + v * dt * math.cos(th), y + v * dt * math.sin(th), th + w * dt, s + abs(v) * dt
        got = path_gap_mm([point], left, right)
        assert abs(got - want) <= 3 or (want == FAR_MM and got >= 1000), (left, right, point, got, want)
        checked += 1
        turning_hits += want != FAR_MM and left != right
    assert turning_hits > 20


def test_a_block_corner_the_robot_arcs_into_stops_it_and_the_controller_knows_its_maps_corners():
    """The corner of a map block between two sensors' cones: straight ahead it is beside the swept
    corridor, but the arc the command drives runs into it."""
    from firmware_py.control.collision import MapCorners, path_gap_mm, robot_frame
    from firmware_py.mapdata import OccupancyGrid

    corner = robot_frame([(1000, 1160)], (800, 1000, 0))  # 200 mm ahead, 160 mm left
    assert path_gap_mm(corner, 300, 300) == FAR_MM  # straight on: it passes beside
    assert path_gap_mm(corner, 200, 300) < 200  # curving left into it: within the slow zone
    nothing = ([2000] * N, [FAR] * N)
    assert limit(200, 300, *nothing, 50, 200, 50, corner)[2] in ("slow", "stop")
    # a 3 x 3 map of 500 mm cells with its centre cell occupied: that block's four corners, no others
    grid = OccupancyGrid(cell_mm=500, width=3, height=3, occ=bytes([0, 0, 0, 0, 1, 0, 0, 0, 0]))
    corners = MapCorners(grid)
    assert sorted(corners.near(750, 750, 1000)) == [(500, 500), (500, 1000), (1000, 500), (1000, 1000)]
    assert corners.near(250, 250, 200) == []  # none within 200 mm of the south-west cell's centre
