"""Manual mode (issue 30): MANUAL_CONTROL sticks drive the wheels, a deadman
stops them 500 ms (control clock) after the last sample, and safety wins -
disarm, Hold, the GCS failsafe, e-stop, stale sensors; the bumper passes
only reversing. Driven on the real Controller with a kinematic plant, and
the sticks through the MAVLink node's real parser."""

from __future__ import annotations

import pytest

from firmware_py import robot_spec
from firmware_py.control.manual import DEADMAN_US, ManualSticks
from firmware_py.vehicle import CtrlState, Mode
from tests.firmware_py.test_controller_core import armed_rig
from tests.firmware_py.test_mav_engines import Link

P = robot_spec.CONTROL_PERIOD_US
VMAX = robot_spec.MAX_WHEEL_SPEED_MM_S


def _manual(rig):
    assert rig.ctrl.set_mode(Mode.MANUAL) == (True, "")
    return rig.ctrl


def test_sticks_drive_and_the_deadman_stops_within_half_a_second():
    rig = armed_rig(None, pose=(1000, 1000, 0))  # no policy: Manual needs none (bring-up by hand)
    ctrl = _manual(rig)
    x0 = rig.plant.x
    for _ in range(10):
        ctrl.manual_control(500, 0, rig.t)  # half stick forward, sent every tick
        rig.tick()
    assert rig.last_motor.left_mm_s == rig.last_motor.right_mm_s == VMAX // 2
    assert rig.plant.x > x0 + 100  # it moved forward (heading 0: +x)
    last = rig.t - P
    while rig.t - last <= DEADMAN_US:
        rig.tick()
        assert (rig.last_motor.left_mm_s, rig.last_motor.right_mm_s) == (VMAX // 2, VMAX // 2)
    rig.tick()
    assert (rig.last_motor.left_mm_s, rig.last_motor.right_mm_s) == (0, 0)  # released: stopped


def test_turning_stick_and_full_deflection_stay_inside_the_speed_limit():
    s = ManualSticks()
    s.update(0, 1000, 0)
    assert s.wheels(0, VMAX, bumper=False) == (VMAX, -VMAX)  # r > 0: clockwise, left wheel forward
    s.update(1000, 1000, 0)
    left, right = s.wheels(0, VMAX, bumper=False)
    assert left == VMAX and right == 0
    assert not s.update(1001, 0, 0) and s.refused == 1  # out of range: refused, the last sample kept
    s.update(800, 0x7FFF, 0)  # INT16_MAX: an axis the sender does not use
    assert s.wheels(0, VMAX, bumper=False) == (VMAX * 8 // 10, VMAX * 8 // 10)
    assert s.wheels(0, VMAX, bumper=True) == (0, 0)  # pressed: no pushing on
    s.update(-800, 0, 0)
    assert s.wheels(0, VMAX, bumper=True) == (-VMAX * 8 // 10, -VMAX * 8 // 10)  # backing off is allowed


@pytest.mark.parametrize("stop", ["hold", "disarm", "failsafe", "estop", "stale"])
def test_safety_wins_over_the_sticks(stop):
    rig = armed_rig(None, pose=(1000, 1000, 0))
    ctrl = _manual(rig)
    for _ in range(3):
        ctrl.manual_control(1000, 0, rig.t)
        rig.tick()
    assert rig.last_motor.left_mm_s > 0
    overrides = {}
    if stop == "hold":
        ctrl.set_mode(Mode.HOLD)
    elif stop == "disarm":
        ctrl.disarm()
    elif stop == "failsafe":
        ctrl.set_failsafe(True)  # FS_GCS_ACTION Hold by default
    elif stop == "estop":
        overrides = {"estop": True}
    ctrl.manual_control(1000, 0, rig.t)
    if stop == "stale":
        rig.tick(fresh=False)  # the last inputs again, never refreshed
        for _ in range(ctrl.cfg.sensor_timeout_ms * 1000 // P + 1):
            ctrl.manual_control(1000, 0, rig.t)
            rig.tick(fresh=False)
        assert ctrl.state == CtrlState.FAULT
    else:
        rig.tick(**overrides)
    assert (rig.last_motor.left_mm_s, rig.last_motor.right_mm_s) == (0, 0), stop
    ctrl.manual_control(1000, 0, rig.t)
    rig.tick(**overrides)
    assert (rig.last_motor.left_mm_s, rig.last_motor.right_mm_s) == (0, 0), stop


def test_manual_control_reaches_the_vehicle_through_the_node():
    link = Link()
    gcs = link.gcs
    link.send(gcs.manual_control_encode(1, 300, 0, 500, -200, 0))
    link.send(gcs.manual_control_encode(7, 300, 0, 500, -200, 0))  # another system's sticks: ignored
    assert link.vehicle.manual_samples == [(300, -200, link.now)]
