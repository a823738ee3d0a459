"""Motor driver model: response, limits, sim-time watchdog, e-stop latch, stall flags."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_py import can_protocol as cp
from firmware_py import robot_spec
from sim_bridge.motors import MotorDriver, MotorParams
from sim_bridge.plant import Plant, SimConfig
from sim_bridge.world import Pose

DT_US = robot_spec.PHYSICS_DT_US


def _run(m: MotorDriver, t_us: int, until_us: int) -> tuple[int, list[tuple[float, float]]]:
    out = []
    while t_us < until_us:
        t_us += DT_US
        out.append(m.step(DT_US, t_us))
    return t_us, out


def test_first_order_response_respects_accel_and_speed_limits():
    p = MotorParams(time_constant_s=0.05, accel_limit_mm_s2=3000.0)
    m = MotorDriver(p)
    speeds = []
    for k in range(10):  # a command every 100 ms keeps the watchdog fed
        m.command(600, -300, k, k * 100_000)
        speeds += _run(m, k * 100_000, (k + 1) * 100_000)[1]
    prev = (0.0, 0.0)
    for s in speeds:
        for i in (0, 1):
            assert abs(s[i] - prev[i]) <= p.accel_limit_mm_s2 * DT_US / 1e6 + 1e-9
            assert abs(s[i]) <= robot_spec.MAX_WHEEL_SPEED_MM_S
        prev = s
    assert speeds[-1] == pytest.approx((600.0, -300.0), abs=1e-6)
    assert m.status()["Mot_AccelLimited"] == 1
    m.command(10_000, 0, 2, 1_000_000)  # beyond the DBC range: clamped by the driver
    _run(m, 1_000_000, 1_150_000)
    assert m.speed[0] == robot_spec.MAX_WHEEL_SPEED_MM_S


def test_watchdog_stops_the_wheels_within_its_timeout_in_sim_time():
    p = MotorParams(watchdog_ms=200, accel_limit_mm_s2=3000.0)
    m = MotorDriver(p)
    assert m.status()["Mot_State"] == cp.MOTOR_IDLE
    m.command(600, 600, 7, 0)
    t, _ = _run(m, 0, 200_000 - DT_US)  # fed at t=0: still running just before the timeout
    assert m.status()["Mot_State"] == cp.MOTOR_RUNNING and m.speed[0] > 500
    t, _ = _run(m, t, 200_000)
    st = m.status()
    assert st["Mot_WatchdogTripped"] == 1 and st["Mot_State"] == cp.MOTOR_WATCHDOG_STOP
    assert m.target == [0.0, 0.0] and m.speed == [0.0, 0.0]  # zeroed at the timeout
    t, speeds = _run(m, t, 400_000)
    assert all(s == (0.0, 0.0) for s in speeds)
    m.command(100, 100, 8, t)  # a fresh command clears the trip
    assert m.status()["Mot_WatchdogTripped"] == 0 and m.status()["Mot_CmdCounterLsb"] == 8


def test_watchdog_trips_in_the_plant_when_commands_stop_and_reports_on_can():
    plant = Plant(np.zeros((6, 6), bool), SimConfig(), Pose(0.5, 1.5, 0.0))
    plant.tick_frames()
    assert plant.handle(cp.motor_command(400, 400, 0))
    plant.step_period()
    watchdog_ticks = plant.config.motors.watchdog_ms * 1000 // robot_spec.CONTROL_PERIOD_US
    for _ in range(watchdog_ticks - 2):  # no more commands: 150 ms since the last one
        plant.step_period()
    status = dict(cp.decode(plant.tick_frames()[4])[1])
    assert status["Mot_WatchdogTripped"] == 0
    plant.step_period()
    frames = plant.tick_frames()
    name, status = cp.decode(frames[4])
    assert name == "MotorStatus" and status["Mot_WatchdogTripped"] == 1
    for _ in range(10):
        plant.step_period()
    x = plant.world.pose.x
    for _ in range(10):
        plant.step_period()
    assert plant.world.pose.x == pytest.approx(x, abs=1e-4)  # stopped


def test_estop_latches_until_released():
    m = MotorDriver()
    m.command(300, 300, 1, 0)
    _run(m, 0, 200_000)
    m.estop(True)
    m.command(300, 300, 2, 200_000)  # ignored while latched
    t, _ = _run(m, 200_000, 500_000)
    st = m.status()
    assert st["Mot_State"] == cp.MOTOR_ESTOP and st["Mot_EStop"] == 1 and m.speed == [0.0, 0.0]
    m.estop(False)
    assert m.status()["Mot_State"] == cp.MOTOR_IDLE
    m.command(300, 300, 3, t)
    _run(m, t, t + 150_000)  # inside the watchdog timeout
    assert m.status()["Mot_State"] == cp.MOTOR_RUNNING and m.speed[0] > 250


def test_plant_applies_estop_frames_and_flags_stall_against_a_wall():
    occ = np.zeros((4, 6), bool)
    plant = Plant(occ, SimConfig(), Pose(2.5, 1.0, 0.0))  # 0.35 m from the east wall
    for _ in range(30):
        plant.tick_frames()
        plant.handle(cp.motor_command(400, 400, plant.tick))
        plant.step_period()
    status = cp.decode(plant.tick_frames()[4])[1]
    assert status["Mot_Errors"] & cp.MOTOR_ERR_STALL_LEFT and status["Mot_Errors"] & cp.MOTOR_ERR_STALL_RIGHT
    plant.handle(cp.encode("EStop", {"EStop_Engage": 1, "EStop_Source": cp.NODE_SIM,
                                     "EStop_Reason": 4}))
    plant.handle(cp.motor_command(-400, -400, plant.tick))  # ignored while latched
    for _ in range(5):
        plant.step_period()
    status = cp.decode(plant.tick_frames()[4])[1]
    assert status["Mot_State"] == cp.MOTOR_ESTOP and status["Mot_LeftSpeed"] == 0


def test_params_are_validated():
    with pytest.raises(ValueError, match="watchdog"):
        MotorDriver(MotorParams(watchdog_ms=0))
    with pytest.raises(ValueError, match="speed limit"):
        MotorDriver(MotorParams(speed_limit_mm_s=robot_spec.MAX_WHEEL_SPEED_MM_S + 1))
