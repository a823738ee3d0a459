"""The plant's battery (sim_bridge/battery.py) and its way to a ground station: the voltage sags
with the wheels' load and falls as charge is used; the plant sends BatteryStatus at 2 Hz; the
robot reports it as BATTERY_STATUS and in SYS_STATUS, and as unknown when no power board speaks."""

from __future__ import annotations

from firmware_py import can_protocol as cp
from sim_bridge.battery import Battery, BatteryParams, open_circuit_volts


def test_voltage_sags_under_load_and_charge_runs_down_in_sim_time():
    full = Battery()
    idle_v = full.volts
    full.step(0.05, 300, 300)
    assert full.volts < idle_v - 0.05  # 1.8 A more through 60 mOhm
    assert abs(open_circuit_volts(1.0, 3) - 12.6) < 1e-9 and abs(open_circuit_volts(0.0, 3) - 9.81) < 1e-9
    small = Battery(BatteryParams(capacity_mah=100.0))
    for _ in range(600):  # 30 s at full speed: 2.2 A from 100 mAh
        small.step(0.05, 300, 300)
    assert 0.0 <= small.soc < 0.85 and small.status(1)["Bat_Remaining"] == round(small.soc * 100)


def test_the_plant_sends_battery_status_twice_a_second_and_the_robot_reports_it():
    import numpy as np

    from firmware_py.control.controller import Controller
    from firmware_py.control.node import InputTracker
    from firmware_py.mavlink.dialect import mavlink2 as m
    from firmware_py.mavlink.params import ParamStore
    from firmware_py.mavlink.telemetry import NodeStats, Telemetry
    from sim_bridge.plant import Plant

    plant = Plant(np.zeros((4, 4), dtype=bool))
    tracker = InputTracker(defer_stamps=False)
    batteries = 0
    for _ in range(20):  # one second of ticks
        for f in plant.tick_frames():
            name, sig = cp.decode(f)
            batteries += name == "BatteryStatus"
            tracker.apply(name, sig, plant.time_us)
        plant.step_period()
    assert batteries == 2
    ctrl = Controller()
    telemetry = Telemetry(m.MAVLink(None, 1, 1), ParamStore(None))
    assert telemetry.build(m.MAVLINK_MSG_ID_BATTERY_STATUS, 0, ctrl.status(), NodeStats()) == []  # none heard
    ctrl.step(tracker.snapshot(), plant.time_us)
    st = ctrl.status()
    assert 12000 < st.battery_mv < 12700 and st.battery_pct == 100 and st.battery_ma >= 400
    (bat,) = telemetry.build(m.MAVLINK_MSG_ID_BATTERY_STATUS, plant.time_us, st, NodeStats())
    assert bat.voltages[0] == st.battery_mv and bat.voltages[1] == 0xFFFF and bat.battery_remaining == 100
    (sys,) = telemetry.build(m.MAVLINK_MSG_ID_SYS_STATUS, plant.time_us, st, NodeStats())
    assert sys.voltage_battery == st.battery_mv and sys.battery_remaining == 100
    ctrl.step(tracker.snapshot(), plant.time_us + 6_000_000)  # the board fell silent: unknown, not full
    assert ctrl.status().battery_pct == -1
