"""SYSTEM_TIME (issue 15, "sim time end to end"): the robot streams its two
clocks at 1 Hz - time_boot_ms, its control clock (sim time in HIL), and
time_unix_usec, its wall clock or 0 when that was never set - and the
ground station's VehicleView (monitor and report) runs its clock on it."""

from __future__ import annotations

from firmware_py.mavlink.dialect import mavlink2 as mavlink
from firmware_py.mavlink.params import ParamStore
from firmware_py.mavlink.telemetry import WALL_CLOCK_SET_AFTER_US, NodeStats, Telemetry
from firmware_py.vehicle import Mode, VehicleStatus
from ground_station.monitor.model import VehicleView
from ground_station.monitor.report import _robot_wall_clock
from tests.ground_station.test_monitor_model import feed, heartbeat, wire
from tests.support.rover_script import encoder

WALL_2026_US = 1_795_000_000_000_000


def system_times(tel: Telemetry, t0_us: int, t1_us: int, step_us: int = 50_000) -> list:
    st = VehicleStatus(time_us=t0_us, mode=Mode.HOLD)
    out = []
    for now in range(t0_us, t1_us, step_us):  # the control tick's 20 Hz
        out += [m for m in tel.due(now, st, NodeStats()) if m.get_msgId() == mavlink.MAVLINK_MSG_ID_SYSTEM_TIME]
    return out


def test_system_time_streams_at_1hz_on_the_robot_clock_with_its_wall_clock():
    tel = Telemetry(encoder(1, 1), ParamStore(None), wall_us=lambda: WALL_2026_US)
    msgs = system_times(tel, 82_000_000, 87_000_000)  # five seconds of (sim) robot time
    assert [m.time_boot_ms for m in msgs] == [82_000, 83_000, 84_000, 85_000, 86_000]
    assert {m.time_unix_usec for m in msgs} == {WALL_2026_US}


def test_system_time_says_0_when_the_robot_wall_clock_was_never_set():
    tel = Telemetry(encoder(1, 1), ParamStore(None), wall_us=lambda: 3_600_000_000)  # an RTC-less board: 1970
    (msg,) = system_times(tel, 0, 1_000_000)
    assert msg.time_unix_usec == 0 and msg.time_boot_ms == 0
    tel = Telemetry(encoder(1, 1), ParamStore(None), wall_us=lambda: WALL_CLOCK_SET_AFTER_US)
    assert system_times(tel, 0, 1_000_000)[0].time_unix_usec == WALL_CLOCK_SET_AFTER_US


def test_system_time_alone_drives_the_views_robot_clock():
    mav = encoder(1, 1)
    tel = Telemetry(mav, ParamStore(None), wall_us=lambda: WALL_2026_US)
    view = VehicleView()
    feed(view, wire(mav, heartbeat()), t=1000.0)
    assert view.robot_clock() is None and view.robot_unix_us is None
    # the robot's time runs 10x the receive time (a lockstep sim): the view follows the robot
    for i, msg in enumerate(system_times(tel, 10_000_000, 15_000_000)):
        feed(view, wire(mav, msg), t=1000.0 + 0.1 * i)
    assert view.robot_clock() == 4.0
    assert view.robot_unix_us == WALL_2026_US
    assert _robot_wall_clock(view.robot_unix_us) == "2026-11-18T11:06:40+00:00"
    assert _robot_wall_clock(0) == "unset" and _robot_wall_clock(None) is None
