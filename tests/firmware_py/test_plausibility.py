"""Plausibility of what the bus says (issue 13): far-future SimTicks, encoder
jumps and sensor boards stuck re-sending one frame. The controller and the
clock are driven directly; the SimTick path once more through RobotNode on a
python-can virtual bus."""

from __future__ import annotations

import math

import can
import pytest

from firmware_py import can_protocol as cp
from firmware_py import robot_spec
from firmware_py.clock import MAX_TICK_JUMP_US, RESYNC_TICKS, SimClock
from firmware_py.control.controller import Controller
from firmware_py.control.node import RobotNode
from firmware_py.vehicle import CtrlState
from tests.firmware_py.test_controller_core import armed_rig
from tests.firmware_py.test_controller_node import expect, sensor_frames, warm_up
from tests.support.controller_rig import sector_seek_policy

P = robot_spec.CONTROL_PERIOD_US


def test_sim_clock_refuses_a_far_jump_and_keeps_following_real_ticks():
    c = SimClock()
    assert c.set_us(120_000_000)  # the first tick is taken: a robot joining a running sim
    assert not c.set_us(10**12) and c.refused_jumps == 1 and c.now_us() == 120_000_000
    for _ in range(5):  # the same forged value again and again never resyncs
        assert not c.set_us(10**12)
    assert c.set_us(120_000_000 + P) and c.now_us() == 120_000_000 + P
    assert c.set_us(120_000_000 + P + MAX_TICK_JUMP_US)  # at the bound: still taken
    # the sim really jumped (ticks lost): RESYNC_TICKS consecutive agreeing ticks move the clock
    t0 = c.now_us() + 5_000_000
    taken = [c.set_us(t0 + i * P) for i in range(RESYNC_TICKS)]
    assert taken == [False] * (RESYNC_TICKS - 1) + [True] and c.now_us() == t0 + (RESYNC_TICKS - 1) * P


def test_encoder_jump_is_a_fault_with_the_reason_and_does_not_move_the_pose():
    rig = armed_rig(sector_seek_policy())
    ctrl = rig.ctrl
    assert ctrl.go_to(3000, 250)[0]
    for _ in range(5):
        rig.tick()
    assert ctrl.state == CtrlState.DRIVING
    pose = ctrl.odom.pose_mm()
    inp = rig.inp
    rig.tick(fresh=False, enc_left=inp.enc_left + 1_000_000, enc_us=rig.t)
    assert ctrl.state == CtrlState.FAULT and ctrl.fault.startswith("encoder jump: left 1000000 ticks/50 ms")
    assert abs(ctrl.odom.x_mm - pose[0]) < 100 and abs(ctrl.odom.y_mm - pose[1]) < 100
    assert rig.commands[-1] is None or (rig.commands[-1].left_mm_s, rig.commands[-1].right_mm_s) == (0, 0)
    assert ctrl.encoder_jumps == 1
    rig.tick(fresh=False, enc_us=rig.t)  # the next (plausible) sample integrates from the new reference
    assert abs(ctrl.odom.x_mm - pose[0]) < 100


def test_fast_but_possible_wheels_are_not_a_jump():
    rig = armed_rig(None)
    ctrl = rig.ctrl
    ticks_per_period = robot_spec.MAX_WHEEL_SPEED_MM_S * P * robot_spec.ENCODER_TICKS_PER_REV // (
        robot_spec.wheel_circumference_nm())  # mm/s x us = nm
    left = rig.inp.enc_left
    for _ in range(10):
        left += ticks_per_period  # full speed
        rig.tick(fresh=False, enc_left=left, enc_us=rig.t, ranges_us=[rig.t, rig.t], bumper_us=rig.t,
                 driver_us=rig.t)
    assert ctrl.state == CtrlState.HOLD and ctrl.encoder_jumps == 0


@pytest.mark.parametrize("over", [0, 1])
def test_encoder_jump_limit_is_the_boundary(over):
    """A count change of exactly encoder_jump_limit(dt) is plausible; one tick more is a jump.
    The limit is ENC_JUMP_MARGIN x full wheel speed (plus the slack), worked out here in floats."""
    from firmware_py.control.plausibility import (
        ENC_JUMP_MARGIN,
        ENC_JUMP_SLACK_TICKS,
        encoder_jump_limit,
    )

    full_speed_ticks = (robot_spec.MAX_WHEEL_SPEED_MM_S * P / 1e6) / (2 * math.pi * robot_spec.WHEEL_RADIUS_MM) \
        * robot_spec.ENCODER_TICKS_PER_REV
    limit = encoder_jump_limit(P)
    assert abs(limit - (ENC_JUMP_MARGIN * full_speed_ticks + ENC_JUMP_SLACK_TICKS)) <= 1
    rig = armed_rig(None)
    ctrl = rig.ctrl
    rig.tick(fresh=False, enc_us=rig.t)  # a reference sample
    right = rig.inp.enc_right + limit + over
    rig.tick(fresh=False, enc_right=right, enc_us=rig.t, ranges_us=[rig.t, rig.t], bumper_us=rig.t, driver_us=rig.t)
    assert ctrl.encoder_jumps == over
    assert (ctrl.state == CtrlState.FAULT) == bool(over), ctrl.fault
    if over:
        assert ctrl.fault.startswith(f"encoder jump: right {limit + 1} ticks/{P // 1000} ms (max {limit})")


@pytest.mark.parametrize("frozen", ["enc", "ranges1", "bumper", "driver"])
def test_a_sensor_frame_whose_counter_stops_goes_stale_within_the_timeout(frozen):
    rig = armed_rig(sector_seek_policy())
    ctrl = rig.ctrl
    assert ctrl.go_to(3000, 250)[0]
    counters = {"ranges0": 0, "ranges1": 0, "enc": 0, "bumper": 0, "driver": 0}  # driver: MotorStatus
    t_frozen = None
    tmo = ctrl.cfg.sensor_timeout_ms * 1000
    for k in range(40):
        if k == 10:
            t_frozen = rig.t - P  # the last frame with a new counter came with the previous tick
        for key in counters:
            if not (key == frozen and k >= 10):
                counters[key] = (counters[key] + 1) % cp.SENSOR_COUNTER_MODULUS
        rig.tick(counters=dict(counters))  # the frames keep arriving (fresh stamps), one counter does not
        if ctrl.state == CtrlState.FAULT:
            break
    assert ctrl.state == CtrlState.FAULT and "frozen" in ctrl.fault, ctrl.fault
    assert ("motor driver status" in ctrl.fault) == (frozen == "driver")
    t_fault = ctrl.transitions[-1].t_us
    assert tmo < t_fault - t_frozen <= tmo + P
    assert rig.commands[-1] is None or (rig.commands[-1].left_mm_s, rig.commands[-1].right_mm_s) == (0, 0)


def test_robot_node_drops_a_far_future_sim_tick_and_keeps_detecting_stale_sensors():
    ch = "plausibility-lockstep"
    sim = can.Bus(interface="virtual", channel=ch)
    ctrl = Controller(policy=sector_seek_policy(), lockstep=True)
    node = RobotNode(can.Bus(interface="virtual", channel=ch), ctrl, SimClock(), lockstep=True)
    node.start()
    try:
        t = warm_up(sim, 3)
        assert ctrl.arm() == (True, "") and ctrl.go_to(3000, 0)[0]
        sim.send(cp.sim_tick(3, 10**12))  # forged: far in the future, the next counter
        for f in sensor_frames():
            sim.send(f)
        sim.send(cp.sim_tick(3, t))  # the real tick 3: answered and stepped (not taken as a resend)
        cmd = expect(sim, "MotorCommand")
        assert cmd["Cmd_Counter"] == 3 and node.clock.now_us() == t and node.ticks == 4
        assert node.tick_gate.refused + node.clock.refused_jumps == 1 and node.overruns == 0
        last_fresh, k = t, 3
        while True:  # sensors stop, ticks go on: stale within the timeout + one period
            k += 1
            t += P
            sim.send(cp.sim_tick(k, t))
            cmd = expect(sim, "MotorCommand")
            if cmd["Cmd_LeftSpeed"] == 0 and ctrl.state == CtrlState.FAULT:
                break
            assert t - last_fresh <= 250_000
        assert 250_000 < t - last_fresh <= 250_000 + P
    finally:
        node.stop()
        node.bus.shutdown()
        sim.shutdown()


def test_a_valid_reading_beyond_the_sensor_range_is_taken_as_invalid():
    """RangeSectors frames decoded by the node: a VALID 4095 mm from a 2000 mm sensor (a broken or
    forged frame) reaches the controller as INVALID; in-range readings and other statuses as sent."""
    from firmware_py import can_protocol as cp
    from firmware_py.control.node import InputTracker

    tracker = InputTracker(defer_stamps=False)
    sig = {"Rng0_Counter": 1}
    readings = [(4095, robot_spec.RANGE_VALID), (robot_spec.RANGE_MAX_MM, robot_spec.RANGE_VALID),
                (4095, robot_spec.RANGE_TOO_FAR), (150, robot_spec.RANGE_VALID)]
    for i, (mm, st) in enumerate(readings):
        sig[f"Range{i}"], sig[f"Range{i}Status"] = mm, st
    msg = cp.encode("RangeSectors0", sig)
    name, decoded = cp.decode(msg)
    assert tracker.apply(name, decoded, 1000)
    from firmware_py.control.io import sensor_view
    from firmware_py.layout import DEFAULT, Layout

    inp = sensor_view(tracker.snapshot(), DEFAULT)  # as the controller reads it
    assert inp.range_status[:4] == [robot_spec.RANGE_INVALID, robot_spec.RANGE_VALID,
                                    robot_spec.RANGE_TOO_FAR, robot_spec.RANGE_VALID]
    assert inp.ranges_mm[:4] == [4095, robot_spec.RANGE_MAX_MM, 4095, 150]
    # the limit is each sensor's own range, from the robot profile (issue 44): a 4095 mm sensor keeps it
    far = sensor_view(tracker.snapshot(), Layout(max_ranges_mm=(4095,) + (2000,) * 7))
    assert far.range_status[:2] == [robot_spec.RANGE_VALID, robot_spec.RANGE_VALID]


def test_tick_gate_takes_only_ticks_whose_counter_and_time_agree():
    """Issue 29 finding 6, the pure rule (firmware_py/clock.py)."""
    from firmware_py.clock import MAX_TICK_GAP, TickGate

    p = robot_spec.CONTROL_PERIOD_US

    last: dict[int, int] = {}  # id(gate) -> counter of its last taken tick (as RobotNode keeps it)

    def run(gate, ticks, resends):
        out = []
        for c, t in ticks:
            gap = c - last[id(gate)] if id(gate) in last else 0
            ok = gate.admit(c, t, gap, resends=resends)
            if ok:
                gate.taken(t)
                last[id(gate)] = c
            out.append(ok)
        return out

    g = TickGate()
    assert run(g, [(10, 500_000), (11, 500_000 + p), (12, 500_000 + 2 * p)], True) == [True] * 3
    assert g.period_us == p
    # the next counter 240 ms on (under the clock's 250 ms bound): refused, the real one taken
    assert run(g, [(13, 500_000 + 2 * p + 240_000), (13, 500_000 + 3 * p)], True) == [False, True]
    assert g.refused == 1
    # lockstep: a tick skipping counts is taken once the sim's resends confirmed it
    skip = (16, 500_000 + 6 * p)
    assert run(g, [skip] * RESYNC_TICKS, True) == [False] * (RESYNC_TICKS - 1) + [True]
    # paced (no resends: frames lost): at once, if counter and time agree
    paced = TickGate()
    assert run(paced, [(0, 0), (1, p), (5, 5 * p), (7, 9 * p)], False) == [True, True, True, False]
    # never more than MAX_TICK_GAP counts in one step
    assert run(paced, [(5 + MAX_TICK_GAP + 1, (5 + MAX_TICK_GAP + 1) * p)] * 4, False) == [False] * 4
