"""The controller state machine, driven directly (no threads, no bus) against
an ideal kinematic plant, with real .qtab policies."""

import math

import pytest

from firmware_py import robot_spec
from firmware_py.control.controller import Controller
from firmware_py.control.io import ERR_ESTOP, ERR_SENSOR_STALE
from firmware_py.policy import dump_policy
from firmware_py.vehicle import CtrlState, FailsafeAction, Mode, VehicleConfig
from tests.support.controller_rig import (
    Kinematic,
    Rig,
    cell_bfs_policy,
    fresh_inputs,
    sector_seek_policy,
)

OPEN4 = ["....", "....", "....", "...."]


def armed_rig(policy=None, pose=(250, 250, 0), cfg=None, lockstep=False):
    ctrl = Controller(cfg or VehicleConfig(), policy, start_pose_mm=pose, lockstep=lockstep)
    rig = Rig(ctrl, Kinematic(pose[0], pose[1], pose[2] / 1000))
    rig.tick()
    assert ctrl.arm() == (True, "")
    return rig


def kinds(ctrl):
    return [(t.src.name, t.dst.name) for t in ctrl.transitions]


def sector_rig():  # type: ignore[no-untyped-def]
    """An armed controller with the hand-made sector policy at the origin, and the controller."""
    rig = armed_rig(sector_seek_policy(), pose=(0, 0, 0))
    return rig, rig.ctrl


def test_boot_standby_and_arm_preconditions():
    ctrl = Controller(policy=sector_seek_policy())
    assert ctrl.state == CtrlState.BOOT
    assert ctrl.arm() == (False, "still booting")
    rig = Rig(ctrl, Kinematic(0, 0, 0))
    rig.tick(fresh=False)  # nothing ever received
    assert ctrl.state == CtrlState.STANDBY
    ok, why = ctrl.arm()
    assert not ok and "stale" in why and "ranges0" in why
    rig.tick()
    assert ctrl.arm() == (True, "")
    assert ctrl.state == CtrlState.HOLD and ctrl.armed
    events = ctrl.drain_events()
    assert [e.kind for e in events] == ["transition", "transition"]
    assert "boot complete" in events[0].text and "armed" in events[1].text
    assert ctrl.drain_events() == []


def test_goal_refused_without_arm_or_policy():
    ctrl = Controller(policy=None)
    rig = Rig(ctrl, Kinematic(0, 0, 0))
    rig.tick()
    assert ctrl.go_to(1000, 0) == (False, "disarmed: arm first")
    ctrl.arm()
    assert ctrl.go_to(1000, 0) == (False, "no policy loaded")


def test_sector_policy_drives_to_goal_then_holds():
    rig, ctrl = sector_rig()
    assert ctrl.go_to(1500, 1000) == (True, "")
    assert ctrl.state == CtrlState.DRIVING and ctrl.mode == Mode.GUIDED
    rig.run_until(lambda: ctrl.state == CtrlState.HOLD, 400)
    assert math.hypot(rig.plant.x - 1500, rig.plant.y - 1000) <= robot_spec.GOAL_TOLERANCE_MM + 25
    assert ("DRIVING", "GOAL_REACHED") in kinds(ctrl) and ("GOAL_REACHED", "HOLD") in kinds(ctrl)
    # every command came from the action table, and the robot stops after the goal
    sent = [c for c in rig.commands if c is not None]
    speeds = {(c.left_mm_s, c.right_mm_s) for c in sent}
    assert speeds <= set(robot_spec.ACTION_WHEEL_SPEEDS_MM_S) | {(0, 0)}
    assert (sent[-1].left_mm_s, sent[-1].right_mm_s) == (0, 0)
    for _ in range(10):
        rig.tick()
    assert rig.commands[-1] is None  # not driving, not lockstep: the driver watchdog holds


def test_cell_policy_drives_cell_by_cell_to_the_target():
    lines = ["....", ".@@.", "....", "...."]
    pol = cell_bfs_policy(lines, [(3, 0), (0, 3)])
    start = robot_spec.cell_center_mm(0, 0, 4)
    rig = armed_rig(pol, pose=(*start, -1571))  # facing south
    ctrl = rig.ctrl
    goal = robot_spec.cell_center_mm(0, 3, 4)
    assert ctrl.go_to(*goal) == (True, "")
    visited = []

    def track():
        cell = robot_spec.world_to_cell(int(rig.plant.x), int(rig.plant.y), 4)
        if not visited or visited[-1] != cell:
            visited.append(cell)
        return ctrl.state == CtrlState.HOLD

    rig.run_until(track, 600)
    assert visited == [(0, 0), (0, 1), (0, 2), (0, 3)]
    assert math.hypot(rig.plant.x - goal[0], rig.plant.y - goal[1]) <= robot_spec.GOAL_TOLERANCE_MM
    # the other target of the same table
    goal2 = robot_spec.cell_center_mm(3, 0, 4)
    assert ctrl.go_to(*goal2) == (True, "")
    rig.run_until(lambda: ctrl.state == CtrlState.HOLD, 1200)
    assert math.hypot(rig.plant.x - goal2[0], rig.plant.y - goal2[1]) <= robot_spec.GOAL_TOLERANCE_MM


def test_cell_goal_must_be_a_policy_target():
    rig = armed_rig(cell_bfs_policy(OPEN4, [(3, 3)]))
    ok, why = rig.ctrl.go_to(*robot_spec.cell_center_mm(2, 2, 4))
    assert not ok and "(2,2) is not a policy target" in why


def test_stale_sensors_fault_and_zero_within_one_period():
    cfg = VehicleConfig(sensor_timeout_ms=250)
    rig = armed_rig(sector_seek_policy(), pose=(0, 0, 0), cfg=cfg)
    ctrl = rig.ctrl
    ctrl.go_to(5000, 0)
    for _ in range(5):
        rig.tick()
    assert rig.commands[-1].left_mm_s == 400
    cut = rig.t - robot_spec.CONTROL_PERIOD_US  # last fresh data
    inp = rig.inp
    while ctrl.state == CtrlState.DRIVING:
        rig.tick(fresh=False)
        inp.enc_us = inp.bumper_us = inp.driver_us = rig.t  # only the ranges go silent
    t_fault = ctrl.transitions[-1].t_us
    assert ctrl.state == CtrlState.FAULT and "ranges0" in ctrl.fault
    assert cut + 250_000 < t_fault <= cut + 250_000 + robot_spec.CONTROL_PERIOD_US
    assert (rig.commands[-1].left_mm_s, rig.commands[-1].right_mm_s) == (0, 0)
    assert rig.ctrl.status().state == CtrlState.FAULT
    # recovery only through disarm, and arm needs fresh data
    assert ctrl.go_to(1000, 0)[0] is False
    ctrl.disarm()
    assert ctrl.state == CtrlState.STANDBY
    rig.tick()
    assert ctrl.arm() == (True, "")
    assert ctrl.state == CtrlState.HOLD


def test_bumper_stops_and_blocks_new_goals():
    rig, ctrl = sector_rig()
    ctrl.go_to(5000, 0)
    rig.tick()
    rig.tick(bumper=True)
    assert ctrl.state == CtrlState.HOLD and ctrl.transitions[-1].cause == "bumper pressed"
    assert (rig.commands[-1].left_mm_s, rig.commands[-1].right_mm_s) == (0, 0)
    assert ctrl.go_to(5000, 0) == (False, "bumper pressed")
    rig.tick()
    assert ctrl.go_to(5000, 0) == (True, "")


def test_estop_latches_until_disarm_and_rearm():
    rig, ctrl = sector_rig()
    ctrl.go_to(5000, 0)
    rig.tick()
    rig.tick(estop=True)
    assert ctrl.state == CtrlState.FAULT and ctrl.fault == "e-stop engaged"
    assert (rig.commands[-1].left_mm_s, rig.commands[-1].right_mm_s) == (0, 0)
    assert rig.ctrl.status().estop
    rig.tick()  # e-stop released: still latched
    assert ctrl.state == CtrlState.FAULT
    assert ctrl._errors & ERR_ESTOP
    assert ctrl.go_to(5000, 0)[0] is False
    ctrl.disarm()
    rig.tick(estop=True)
    assert ctrl.arm() == (False, "e-stop is active")
    rig.tick()
    assert ctrl.arm() == (True, "")
    assert ctrl.go_to(5000, 0) == (True, "")


def test_driver_estop_flag_and_driver_fault():
    rig = armed_rig(sector_seek_policy())
    rig.tick(driver_errors=2)
    assert rig.ctrl.state == CtrlState.FAULT and "motor driver fault 0x02" in rig.ctrl.fault
    rig.ctrl.disarm()
    rig.tick(driver_errors=2)
    assert "motor driver errors" in rig.ctrl.arm()[1]
    rig.tick()
    rig.ctrl.arm()
    rig.tick(driver_estop=True)
    assert rig.ctrl.fault == "e-stop engaged"


def test_wheel_speeds_clamped_to_configured_limit():
    cfg = VehicleConfig(max_wheel_speed_mm_s=300, speed_scale_pct=250)
    rig = armed_rig(sector_seek_policy(), pose=(0, 0, 0), cfg=cfg)
    rig.ctrl.go_to(5000, 3000)
    for _ in range(30):
        rig.tick()
    sent = [c for c in rig.commands if c is not None]
    assert max(max(abs(c.left_mm_s), abs(c.right_mm_s)) for c in sent) == 300


def test_lockstep_answers_every_tick_with_its_counter_and_zero_when_idle():
    ctrl = Controller(policy=sector_seek_policy(), lockstep=True)
    plant = Kinematic(0, 0, 0)
    for k in range(5):
        out = ctrl.step(fresh_inputs(plant, k * 50_000), k * 50_000, tick=k + 100)
        assert out.motor is not None and out.motor.counter == k + 100
        assert (out.motor.left_mm_s, out.motor.right_mm_s) == (0, 0)
        assert out.heartbeat.state == int(ctrl.state)


def test_watchdog_zeroes_a_stalled_decision_path():
    rig = armed_rig(sector_seek_policy(), pose=(0, 0, 0), cfg=VehicleConfig(motor_timeout_ms=200))
    ctrl = rig.ctrl
    ctrl.go_to(5000, 0)
    rig.tick()
    assert ctrl.watchdog.output(rig.t) == (400, 400)
    assert ctrl.watchdog.output(rig.t + 150_000) == (400, 400)
    assert ctrl.watchdog.output(rig.t + 260_000) == (0, 0)
    assert ctrl.watchdog.expirations == 1


def test_policy_hot_swap_refused_while_driving_and_keeps_last_good(tmp_path):
    first = sector_seek_policy(policy_id=11)
    rig = armed_rig(first, pose=(0, 0, 0))
    ctrl = rig.ctrl
    p = tmp_path / "new.qtab"
    enc = first.encoder
    p.write_bytes(dump_policy(enc, first.table.tolist(), "int8", 0.5, policy_id=22, map_geometry=first.map_geometry))
    ctrl.go_to(5000, 0)
    rig.tick()
    assert ctrl.activate_policy(str(p)) == (False, "refused while driving: stop first")
    assert ctrl.policy.policy_id == 11
    ctrl.set_mode(Mode.HOLD)
    assert ctrl.state == CtrlState.HOLD
    bad = tmp_path / "bad.qtab"
    raw = p.read_bytes()
    bad.write_bytes(raw[:-1] + bytes([raw[-1] ^ 0xFF]))  # always breaks the CRC
    ok, why = ctrl.activate_policy(str(bad))
    assert not ok and why.startswith("policy rejected:") and "CRC32" in why
    assert ctrl.policy.policy_id == 11
    assert ctrl.activate_policy(str(p)) == (True, "")
    assert ctrl.policy.policy_id == 22 and ctrl.last_known_good.policy_id == 11
    assert ctrl.status().policy_id == 22
    assert ctrl.revert_policy() == (True, "")
    assert ctrl.policy.policy_id == 11


def test_mission_items_reached_in_order_then_hold():
    rig, ctrl = sector_rig()
    assert ctrl.set_mission([(1000, 0), (1000, 1000)]) == (True, "")
    assert ctrl.start_mission() == (True, "")
    assert ctrl.mode == Mode.AUTO
    seen = []

    def done():
        seen.extend(e for e in ctrl.drain_events() if e.kind == "mission_item_reached")
        return ctrl.state == CtrlState.HOLD

    rig.run_until(done, 600)
    assert [e.seq for e in seen] == [0, 1]
    assert ctrl.mode == Mode.HOLD and ctrl.transitions[-1].cause == "mission complete"
    assert ctrl.set_mission_current(5)[0] is False


def test_gcs_failsafe_holds():
    rig = armed_rig(sector_seek_policy(), pose=(0, 0, 0),
                    cfg=VehicleConfig(gcs_failsafe_action=FailsafeAction.HOLD))
    rig.ctrl.go_to(5000, 0)
    rig.tick()
    rig.ctrl.set_failsafe(True)
    assert rig.ctrl.state == CtrlState.HOLD and rig.ctrl.status().failsafe
    assert any(e.text == "GCS Failsafe" for e in rig.ctrl.drain_events())


def test_error_bits_in_heartbeat():
    ctrl = Controller(policy=sector_seek_policy())
    rig = Rig(ctrl, Kinematic(0, 0, 0))
    out = rig.tick(fresh=False)
    assert out.heartbeat.errors & ERR_SENSOR_STALE
    out = rig.tick()
    assert out.heartbeat.errors == 0 and out.heartbeat.policy_loaded


@pytest.mark.parametrize("heading", [0, 1571, 3142, -1571, 700])
def test_cell_primitive_turns_to_grid_heading_from_any_start_heading(heading):
    pol = cell_bfs_policy(OPEN4, [(3, 1)])
    start = robot_spec.cell_center_mm(1, 1, 4)
    rig = armed_rig(pol, pose=(*start, heading))
    rig.ctrl.go_to(*robot_spec.cell_center_mm(3, 1, 4))
    rig.run_until(lambda: rig.ctrl.state == CtrlState.HOLD, 400)
    assert abs(rig.plant.y - start[1]) < 40  # drove along the row, not diagonally
