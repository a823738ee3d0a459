"""Issue 44, the robot side of "one profile, every stage": the controller's parts read the sensors at
the profile's angles, in its order and count (firmware_py/layout.py), not robot_spec's; the bumper
board is optional.

Before: the collision monitor, the localiser and the planner used robot_spec's eight angles in the
built-in order, so the same sensors listed clockwise left a post 100 mm off the rim at 45 degrees
unseen (an arc into it went unlimited at 120/600 mm/s where the built-in order slows to -60/420); the
loader refused six sensors ("this build reads 8 sectors"); the controller refused to arm without
fresh Bumper frames whatever the profile said.
"""

from __future__ import annotations

import math

import pytest

from firmware_py import robot_spec
from firmware_py.control.controller import Controller
from firmware_py.profile import profile_from_dict
from firmware_py.vehicle import CtrlState, Mode, VehicleConfig
from tests.support.controller_rig import Kinematic, Rig, fresh_inputs

BUILT_IN = (0, 45, 90, 135, 180, -135, -90, -45)
CLOCKWISE = (0, -45, -90, -135, 180, 135, 90, 45)
SIX = (0, 60, 120, 180, -120, -60)
FAR, VALID = robot_spec.RANGE_TOO_FAR, robot_spec.RANGE_VALID


def _profile(angles, **sections):
    sensors = {"angles_deg": list(angles), **sections.pop("sensors", {})}
    return profile_from_dict({"sensors": sensors, **sections}, f"test-{len(angles)}")


def _manual_arc(angles, post_deg: float, post_mm: int, **prof) -> tuple[int, int]:
    """The wheel command the robot sends for the Manual arc 120/600 mm/s (turning left) with one
    sensor, the one looking `post_deg` off the heading, reading `post_mm` (the rest see nothing)."""
    profile = _profile(angles, **prof)
    ctrl = Controller(VehicleConfig(), None, profile=profile)
    rig = Rig(ctrl, Kinematic(1000, 1000, 0))
    n = len(angles)
    k = [round(a) for a in angles].index(post_deg)
    ranges = [robot_spec.RANGE_MAX_MM] * n
    status = [FAR] * n
    ranges[k], status[k] = post_mm, VALID

    def tick():
        inp = fresh_inputs(rig.plant, rig.t)
        inp.ranges_mm, inp.range_status = list(ranges), list(status)
        return rig.tick(fresh=False) if setattr(rig, "inp", inp) is None else None

    tick()
    assert ctrl.arm() == (True, "") and ctrl.set_mode(Mode.MANUAL) == (True, "")
    ctrl.manual_control(600, -400, rig.t)  # forward 360, turning left 240: left 120, right 600 mm/s
    tick()
    m = rig.last_motor
    return m.left_mm_s, m.right_mm_s


def test_the_collision_monitor_slows_an_arc_into_a_post_at_45_degrees_whatever_the_profiles_order():
    free = _manual_arc(BUILT_IN, 45, 1900)
    assert free == (120, 600)  # nothing near: the arc as commanded
    built_in = _manual_arc(BUILT_IN, 45, 100)
    assert built_in == (-60, 420)  # the straight part halved (CM_SLOW_PCT) for the post in the arc
    assert _manual_arc(CLOCKWISE, 45, 100) == built_in  # the same sensors listed clockwise: the same


def test_a_six_sensor_dronecan_profile_loads_and_the_robots_parts_use_its_six_angles():
    prof = _profile(SIX, sensors={"backend": "dronecan"})
    lay = prof.layout()
    assert lay.count == 6 and prof.sensors.sensor_ids == tuple(range(6))
    assert lay.uncovered() == [2, 6]  # the policy's +-90 degree sectors: no sensor within 22.5 degrees
    rs, ss = lay.to_sectors([100, 200, 300, 400, 500, 600], [VALID] * 6)
    assert ss[2] == ss[6] == robot_spec.RANGE_INVALID  # unknown, never free
    assert rs[1] == 200 and rs[3] == 300 and rs[7] == 600  # 45 -> the 60-degree sensor, 135 -> 120, -45 -> -60
    ctrl = Controller(VehicleConfig(), None, profile=prof)
    assert ctrl.monitor.fan.layout.angles_mrad == tuple(round(math.radians(a) * 1000) for a in SIX)
    from firmware_py.mapdata import grid_from_rows

    ok, _ = ctrl.set_robot_map(grid_from_rows(["......", "......", "......"], 500))
    assert ok and ctrl.loc is not None and len(ctrl.loc._beams) == 6  # the localiser's six fans
    # a post 100 mm off the rim at 60 degrees (sensor 1) slows the arc into it
    assert _manual_arc(SIX, 60, 100, sensors={"backend": "dronecan"}) != (120, 600)


def test_qnav_sensors_other_than_eight_are_refused_with_a_clear_line():
    from firmware_py.profile import ProfileError

    with pytest.raises(ProfileError, match="qnav's RangeSectors frames carry exactly 8"):
        _profile(SIX)


@pytest.mark.parametrize("bumper", [True, False])
def test_a_profile_without_a_bumper_board_arms_and_drives(bumper):
    prof = _profile(BUILT_IN, boards={"bumper": bumper})
    ctrl = Controller(VehicleConfig(), None, profile=prof)
    rig = Rig(ctrl, Kinematic(1000, 1000, 0))

    def tick():
        inp = fresh_inputs(rig.plant, rig.t)
        inp.bumper_us = None  # no Bumper frame ever
        rig.inp = inp
        return rig.tick(fresh=False)

    tick()
    ok, why = ctrl.arm()
    if bumper:  # a profile that says it has one: its input must be fresh
        assert not ok and why == "sensor data stale: bumper"
        return
    assert (ok, why) == (True, "") and ctrl.set_mode(Mode.MANUAL) == (True, "")
    for _ in range(20):  # 1 s of half stick: 300 mm/s
        ctrl.manual_control(500, 0, rig.t)
        tick()
    assert ctrl.state == CtrlState.HOLD and ctrl.armed and not ctrl.fault
    assert ctrl.odom.x_mm > 250, ctrl.odom.x_mm  # it drove (odometry from (0, 0))


def test_check_reports_six_sensors_the_uncovered_sectors_and_the_boards_the_profile_names():
    """`qnav-robot --check`'s sensor lines (bringup._sensor_lines) for a six-sensor DroneCAN profile
    without a bumper board: each of the six sensors, the policy sectors none looks along, the bumper
    board named as absent by the profile (not MISSING)."""
    from types import SimpleNamespace

    from firmware_py.bringup import CheckReport, _sensor_lines
    from firmware_py.control.io import Inputs

    prof = _profile(SIX, sensors={"backend": "dronecan"}, boards={"bumper": False})
    inp = Inputs()
    inp.ranges_mm, inp.range_status = [500] * 6, [VALID] * 6
    rep = CheckReport()
    _sensor_lines(SimpleNamespace(inputs=inp, profile=prof, heard={"ranges0": 1, "ranges1": 1}), rep)
    text = "\n".join(rep.lines)
    assert [ln for ln in rep.lines if "range sensor" in ln] == [
        f"ok       range sensor {i} at {a} deg: 500 mm, valid" for i, a in enumerate(SIX)]
    assert "no sensor looks along policy sector(s) 90, -90 deg (read as unknown)" in text
    assert "bumper board (node 36): none in the profile (boards.bumper = false)" in text
    assert rep.problems == [], rep.problems
