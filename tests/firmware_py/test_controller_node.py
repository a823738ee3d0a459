"""RobotNode over a real python-can virtual bus, driven frame by frame from the
test: lockstep answers, retransmitted ticks, sim-time stamping, paced mode."""

import can
import pytest

from firmware_py import can_protocol as cp
from firmware_py import robot_spec
from firmware_py.clock import RESYNC_TICKS, SimClock
from firmware_py.control.controller import Controller
from firmware_py.control.node import RobotNode
from tests.support.controller_rig import sector_seek_policy

_SAMPLE = [0]


def sensor_frames(enc=(0, 0)):
    _SAMPLE[0] += 1  # every call is a new sample: the rolling counters advance
    n = _SAMPLE[0]
    frames = cp.range_frames([(robot_spec.RANGE_MAX_MM, robot_spec.RANGE_TOO_FAR)] * robot_spec.SENSOR_COUNT, n)
    frames.append(cp.encoder_counts(enc[0], enc[1], n))
    frames.append(cp.encode("Bumper", {"Bump_Pressed": 0, "Bump_Front": 0, "Bump_Left": 0, "Bump_Rear": 0,
                                       "Bump_Right": 0, "Bump_Events": 0, "Bump_AngleMrad": 0,
                                       "Bump_Counter": n % cp.SENSOR_COUNTER_MODULUS}))
    frames.append(cp.encode("MotorStatus", {"Mot_State": 1, "Mot_WatchdogTripped": 0, "Mot_EStop": 0,
                                            "Mot_AccelLimited": 0, "Mot_Errors": 0, "Mot_CmdCounterLsb": 0,
                                            "Mot_LeftSpeed": 0, "Mot_RightSpeed": 0,
                                            "Mot_Counter": n % cp.SENSOR_COUNTER_MODULUS}))
    return frames


def expect(bus, name, timeout=2.0):
    """Next frame called `name` (others skipped)."""
    while True:
        msg = bus.recv(timeout=timeout)
        assert msg is not None, f"no {name} frame"
        if cp.frame_name(msg.arbitration_id) == name:
            return cp.decode(msg)[1]


def warm_up(sim, ticks: int) -> int:
    """`ticks` lockstep periods from t = 0, each with a fresh sensor sample, each answered with a
    MotorCommand; the sim time of the next period."""
    t = 0
    for k in range(ticks):
        for f in sensor_frames():
            sim.send(f)
        sim.send(cp.sim_tick(k, t))
        expect(sim, "MotorCommand")
        t += robot_spec.CONTROL_PERIOD_US
    return t


@pytest.fixture
def rig(request):
    ch = f"node-{request.node.name}"
    sim = can.Bus(interface="virtual", channel=ch)
    ctrl = Controller(policy=sector_seek_policy(), lockstep=True)
    node = RobotNode(can.Bus(interface="virtual", channel=ch), ctrl, SimClock(), lockstep=True)
    node.start()
    yield sim, ctrl, node
    node.stop()
    node.bus.shutdown()
    sim.shutdown()


def test_lockstep_answer_retransmission_and_sim_time_stamps(rig):
    sim, ctrl, node = rig
    for k in range(3):
        for f in sensor_frames():
            sim.send(f)
        sim.send(cp.sim_tick(k, k * robot_spec.CONTROL_PERIOD_US))
        hb = expect(sim, "ControllerHeartbeat")
        cmd = expect(sim, "MotorCommand")  # after the heartbeat: the answer is the last frame
        assert cmd["Cmd_Counter"] == k and hb["Ctrl_State"] == ctrl.state
    assert node.ticks == 3
    # sensor frames are stamped with the sim time of the tick that follows them
    snap = node.inputs.snapshot()
    assert snap.ranges_us == [100_000, 100_000] and snap.enc_us == 100_000
    # a retransmitted tick gets the same answer and no second step
    sim.send(cp.sim_tick(2, 100_000))
    assert expect(sim, "MotorCommand")["Cmd_Counter"] == 2
    assert node.ticks == 3
    # a skipped tick (the sim gave up waiting for tick 3's answer) is taken once the sim's
    # resends confirmed it (clock.TickGate), and counts as an overrun
    for _ in range(RESYNC_TICKS):
        sim.send(cp.sim_tick(4, 200_000))
    assert expect(sim, "MotorCommand")["Cmd_Counter"] == 4
    assert node.overruns == 1 and node.tick_gate.refused == RESYNC_TICKS - 1


def test_lockstep_arm_and_drive_then_sensor_silence_faults(rig):
    sim, ctrl, node = rig
    t = warm_up(sim, 2)
    assert ctrl.arm() == (True, "")
    assert ctrl.go_to(3000, 0) == (True, "")
    k = 2
    for f in sensor_frames():
        sim.send(f)
    sim.send(cp.sim_tick(k, t))
    cmd = expect(sim, "MotorCommand")
    assert (cmd["Cmd_LeftSpeed"], cmd["Cmd_RightSpeed"]) == (400, 400)
    last_fresh = t
    while True:  # ticks keep coming, sensors do not
        k += 1
        t += robot_spec.CONTROL_PERIOD_US
        sim.send(cp.sim_tick(k, t))
        cmd = expect(sim, "MotorCommand")
        if cmd["Cmd_LeftSpeed"] == 0:
            break
        assert t - last_fresh <= 250_000
    assert 250_000 < t - last_fresh <= 250_000 + robot_spec.CONTROL_PERIOD_US
    assert ctrl.state.name == "FAULT"


def test_paced_sim_clock_steps_once_per_period_without_answer_counters():
    ch = "node-paced"
    sim = can.Bus(interface="virtual", channel=ch)
    ctrl = Controller(policy=sector_seek_policy())
    node = RobotNode(can.Bus(interface="virtual", channel=ch), ctrl, SimClock())
    node.start()
    try:
        for k in range(4):
            for f in sensor_frames():
                sim.send(f)
            sim.send(cp.sim_tick(1000 + k, k * robot_spec.CONTROL_PERIOD_US))
            expect(sim, "ControllerHeartbeat")
        assert node.ticks == 4
        assert node.clock.now_us() == 3 * robot_spec.CONTROL_PERIOD_US
    finally:
        node.stop()
        node.bus.shutdown()
        sim.shutdown()
