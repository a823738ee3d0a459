"""The textual dashboard under textual's pilot: fed live over real UDP by a
pymavlink rover, and from a tlog replay."""

from __future__ import annotations

import asyncio
import time

import pytest

from firmware_py import robot_spec
from firmware_py.mavlink.dialect import mavlink2 as mavlink
from ground_station.maps import load_map
from ground_station.monitor.app import MonitorApp, heading_arrow
from ground_station.monitor.sources import ReplaySource, open_live
from ground_station.subprocs import free_udp_port
from tests.support.rover_script import CELL_M, MAP_H, RoverScript, UdpRover, write_tlog

ARROWS = set("→↗↑↖←↙↓↘")


def panel(app, name: str) -> str:
    return app.query_one(f"#{name}").content.plain


def arrow_cell(map_text: str) -> tuple[int, int, str]:
    """(col, row, glyph) of the robot in the rendered map (2 chars per cell)."""
    hits = [(i // 2, r, ch) for r, line in enumerate(map_text.splitlines())
            for i, ch in enumerate(line) if ch in ARROWS]
    assert len(hits) == 1, map_text
    return hits[0]


def view_cell(view) -> tuple[int, int]:
    return robot_spec.world_to_cell(int(view.x * 1000), int(view.y * 1000), MAP_H, int(CELL_M * 1000))


async def wait_for(pilot, cond, timeout=20.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        await pilot.pause(0.1)
        if cond():
            return
    raise AssertionError("condition not met in time")


def test_live_dashboard_follows_the_rover_and_sends_commands():
    port = free_udp_port()
    rover = UdpRover(port, speed=3.0)
    source = open_live(f"udpin:127.0.0.1:{port}", tlog=False)
    app = MonitorApp(source, grid_map=load_map("paper10"))
    rover.start()

    async def scenario():
        async with app.run_test(size=(130, 48)) as pilot:
            v = app.view
            await wait_for(pilot, lambda: v.armed and v.ctrl_name == "DRIVING" and v.x is not None)
            await pilot.pause(0.2)
            first_pose, first_vehicle = (v.x, v.y), panel(app, "vehicle")
            assert "ARMED" in first_vehicle and "DRIVING" in first_vehicle and "mode Auto" in first_vehicle
            await wait_for(pilot, lambda: abs(v.x - first_pose[0]) + abs(v.y - first_pose[1]) > 0.4)
            await pilot.pause(0.2)  # let the next redraw land
            vehicle = panel(app, "vehicle")
            assert vehicle != first_vehicle and f"x {v.x:.2f} y {v.y:.2f}" in vehicle
            col, row, glyph = arrow_cell(panel(app, "map"))
            assert (col, row) == view_cell(v) and glyph == heading_arrow(v.heading)
            assert "state" in panel(app, "policy") and "Q-row [0]" in panel(app, "policy")
            assert "heartbeat age" in panel(app, "link") and "unsigned" in panel(app, "link")
            assert "policy id 0x00001092" in vehicle  # 4242, exact from POLICY_ID_HI/LO
            assert "+45°" in panel(app, "sectors")
            await pilot.press("a")
            await wait_for(pilot, lambda: "ACK COMPONENT_ARM_DISARM: ACCEPTED" in panel(app, "log"))
            await pilot.press("h")
            await wait_for(pilot, lambda: any(c[0] == mavlink.MAV_CMD_DO_SET_MODE for c in rover.commands))
            await pilot.press("q")

    try:
        asyncio.run(scenario())
    finally:
        rover.stop()
        source.close()
    assert (mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0) in rover.commands
    assert (mavlink.MAV_CMD_DO_SET_MODE, float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), 4.0) in rover.commands
    assert rover.received.get("HEARTBEAT", 0) >= 1


@pytest.fixture
def tlog(tmp_path):
    path = tmp_path / "run.tlog"
    write_tlog(path, RoverScript())
    return path


def test_replay_through_the_same_view(tlog):
    source = ReplaySource(str(tlog), speed=0)
    grid = load_map("paper10")
    app = MonitorApp(source, grid_map=grid, subtitle="replay")

    async def scenario():
        async with app.run_test(size=(130, 48)) as pilot:
            await wait_for(pilot, lambda: source.finished)
            await pilot.pause(0.3)
            col, row, _ = arrow_cell(panel(app, "map"))
            assert (col, row) == grid.targets["B"]
            mission = panel(app, "mission")
            assert "reached 2 (0, 1)" in mission and "(B)" in mission
            assert "Fault: sensor timeout" in panel(app, "log")
            assert "replay finished" in app.sub_title
            await pilot.press("a")  # no link: refused with a note, nothing crashes
            await pilot.pause(0.1)
            await pilot.press("q")

    try:
        asyncio.run(scenario())
    finally:
        source.close()
    assert "ignored" in source.send_command("arm", (1, 1))


def test_a_long_map_name_is_not_cut_on_a_small_map(tlog, tmp_path):
    """Issue 30 item 7: the map panel is as wide as its cells, and a 5x5 map's name was cut."""
    path = tmp_path / "the-loading-bay-of-the-east-warehouse.map"
    path.write_text("type octile\nheight 5\nwidth 5\nmap\n" + ".....\n" * 5)
    grid = load_map(str(path))
    source = ReplaySource(str(tlog), speed=0)
    app = MonitorApp(source, grid_map=grid, subtitle="replay")

    async def scenario():
        async with app.run_test(size=(130, 48)) as pilot:
            await pilot.pause(0.3)
            widget = app.query_one("#map")
            assert widget.border_title == grid.name
            assert widget.region.width >= len(grid.name) + 4  # the title and its corners fit
            await pilot.press("q")

    try:
        asyncio.run(scenario())
    finally:
        source.close()
