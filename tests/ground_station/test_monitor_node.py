"""The dashboard against the robot's real MAVLink node over UDP (the node
shell + tests/support/mav_vehicle.py's small vehicle state machine): mission
A-D from the monitor's own link, keys arm/hold, the view following it all.
The HIL-driven check (controller + pymunk sim) is the integrator's."""

from __future__ import annotations

import asyncio
import time

from firmware_py import robot_spec
from firmware_py.mavlink.dialect import mavlink2 as mavlink
from ground_station.maps import load_map
from ground_station.monitor.app import MonitorApp
from ground_station.monitor.sources import open_live
from ground_station.subprocs import free_udp_port
from tests.support.mav_vehicle import Robot


def test_dashboard_on_the_real_node(tmp_path):
    port = free_udp_port()
    node = Robot(tmp_path / "storage", port, speed_mm_s=2_000)
    grid = load_map("paper10")
    tlog = tmp_path / "session.tlog"
    source = open_live(f"udpin:127.0.0.1:{port}", tlog=str(tlog))
    link = source.link
    try:
        link.connect(10)
        cells = [grid.targets[n] for n in "ABCD"]
        items = []
        for col, row in cells:
            x_mm, y_mm = robot_spec.cell_center_mm(col, row, grid.height)
            items.append((mavlink.MAV_FRAME_LOCAL_NED, y_mm * 10, x_mm * 10))  # NED metres * 1e4
        assert link.mission_upload(items) == 4
        app = MonitorApp(source, grid_map=grid)

        async def scenario():
            async with app.run_test(size=(130, 48)) as pilot:
                v = app.view

                async def until(cond, timeout=20.0):
                    deadline = time.monotonic() + timeout
                    while time.monotonic() < deadline:
                        await pilot.pause(0.1)
                        if cond():
                            return
                    raise AssertionError(f"timed out; view: {v.status_line(source.now())}")

                await until(lambda: v.mode_name == "Hold" and v.x is not None)
                await pilot.press("a")
                await until(lambda: v.armed)
                assert "ARMED" in app.query_one("#vehicle").content.plain
                link.conn.mav.command_long_send(v.sysid, v.compid, mavlink.MAV_CMD_MISSION_START, 0, 0, 0, 0, 0, 0, 0, 0)
                await until(lambda: v.mode_name == "Auto" and v.ctrl_name == "DRIVING")
                await until(lambda: len(v.mission.reached) >= 2)
                assert v.mission.total == 4 and v.mission.reached[:2] == [0, 1]
                assert v.goal is not None  # POSITION_TARGET_LOCAL_NED from the node
                await pilot.press("h")
                await until(lambda: v.mode_name == "Hold")
                assert "ACK DO_SET_MODE: ACCEPTED" in app.query_one("#log").content.plain
                assert "ACK COMPONENT_ARM_DISARM: ACCEPTED" in [e.text for e in v.log]
                await pilot.press("q")

        asyncio.run(scenario())
    finally:
        source.close()
        node.stop()
    assert app.view.policy_id == 0  # no policy on this vehicle: the read-only param says 0
    assert app.view.link.lost == 0 and app.view.link.received > 50
    from ground_station.monitor.report import analyse, summarise

    s = summarise(analyse(tlog), grid)
    assert [i["seq"] for i in s["mission_items_reached"]][:2] == [0, 1]
    assert [i.get("target") for i in s["mission_items_reached"]][:2] == ["A", "B"]  # items seen on our own link
    assert s["path_length_m"] > 1.0
