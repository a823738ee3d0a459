"""MAVSDK (the PX4 tools' and companion apps' client family; `mavsdk<4`, the
gRPC wrapper with its bundled mavsdk_server) against `qnav sitl --autopilot
ardupilot`: int parameters read with their true values (and one set), the
robot's lack of float parameters seen as such, a policy uploaded over FTP and
activated by a Rename onto /policies/active.qtab, arming with live sensors,
and the flight mode named: HOLD, MISSION in Auto (a mission uploaded and
started with MAVSDK's own mission_raw), OFFBOARD in Guided (MAVSDK's
goto_location), HOLD again.

Why `--autopilot ardupilot`: MAVSDK picks the PARAM_VALUE decoding from the
HEARTBEAT's autopilot field (C cast for ArduPilot, bytewise for anything else;
the PARAM_ENCODE_C_CAST capability bit the robot advertises is not
consulted) and names flight modes only for PX4 and ArduPilot. The generic
case is checked too: its flight mode is UNKNOWN and its int parameters read
as float bits, which is why the option exists (docs/mavlink.md)."""

from __future__ import annotations

import asyncio
import shutil
import signal
from pathlib import Path

import pytest

from firmware_py import robot_spec
from firmware_py.mavlink import frames
from firmware_py.policy import load_policy
from firmware_py.shipped_policies import resolve_policy_spec
from ground_station.subprocs import free_port
from tests.hil.test_sitl import SitlProcess, cell_world_mm

pytestmark = pytest.mark.slow


def mavsdk_or_skip():
    try:
        import mavsdk
    except ImportError as exc:
        pytest.skip(f"mavsdk not installed (dev extra: mavsdk<4): {exc}")
    server = Path(mavsdk.__file__).parent / "bin" / "mavsdk_server"
    if not server.is_file():
        pytest.skip(f"mavsdk_server not bundled at {server}")
    import subprocess

    try:
        subprocess.run([str(server), "--help"], capture_output=True, timeout=20)
    except OSError as exc:
        pytest.skip(f"mavsdk_server cannot run here: {exc}")
    return mavsdk


DRONES: list = []  # every System started, its mavsdk_server stopped at the end of each test


@pytest.fixture(autouse=True)
def stop_mavsdk_servers():
    yield
    while DRONES:
        DRONES.pop()._stop_mavsdk_server()


async def connected(mavsdk, url: str):
    drone = mavsdk.System(port=free_port(), sysid=255)  # the robot takes control from SYSID_MYGCS only
    DRONES.append(drone)
    await drone.connect(system_address=url)
    async for state in drone.core.connection_state():
        if state.is_connected:
            return drone
    raise AssertionError("no connection state")


async def first(stream):
    async for item in stream:
        return item
    raise AssertionError("stream ended")


async def mode_becomes(drone, name: str, timeout_s: float = 20.0) -> bool:
    """True once MAVSDK's flight mode reads `name` (False after `timeout_s`)."""
    async def wait() -> bool:
        async for mode in drone.telemetry.flight_mode():
            if str(mode) == name:
                return True
        return False
    try:
        return await asyncio.wait_for(wait(), timeout_s)
    except TimeoutError:
        return False


def mavsdk_url(sitl: SitlProcess) -> str:
    line = sitl.expect(r'MAVSDK\s+System\(sysid=255\)\.connect\(system_address="(\S+)"\)')
    return line.split('system_address="')[1].split('"')[0]


@pytest.mark.slow  # 10 s: started among the wall-clock pass's first
@pytest.mark.timeout(300)
@pytest.mark.wallclock  # `qnav sitl` in real time and MAVSDK's own FTP/command timeouts
def test_mavsdk_params_ftp_upload_arm_and_flight_mode(tmp_path):
    mavsdk = mavsdk_or_skip()
    from mavsdk.mission_raw import MissionItem
    from mavsdk.param import ParamError

    mavsdk_frame = 6  # MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, as MAVSDK's mission plugin sends

    sitl = SitlProcess(tmp_path, "--autopilot", "ardupilot", "--policy", "none")
    policy_file = tmp_path / "paper10_cell.qtab"
    shutil.copy(resolve_policy_spec("policies:paper10_cell"), policy_file)
    policy = load_policy(policy_file)

    async def scenario() -> None:
        drone = await connected(mavsdk, mavsdk_url(sitl))
        sitl.wait_up()
        # int parameters with their true values, and a set that lands as the number given
        assert await drone.param.get_param_int("GOAL_TOL_MM") == robot_spec.GOAL_TOLERANCE_MM
        assert await drone.param.get_param_int("CTRL_RATE_HZ") == robot_spec.CONTROL_RATE_HZ
        everything = await drone.param.get_all_params()
        ints = {p.name: p.value for p in everything.int_params}
        assert ints["FS_GCS_TOUT_MS"] == 5000 and ints["SYSID_THISMAV"] == 1
        assert everything.float_params == []  # the robot has no float parameter: none invented
        with pytest.raises(ParamError):
            await drone.param.get_param_float("GOAL_TOL_MM")  # an INT32 stays one
        await drone.param.set_param_int("GOAL_TOL_MM", 250)
        assert await drone.param.get_param_int("GOAL_TOL_MM") == 250
        # FTP: upload, CRC compare, Rename onto active.qtab -> the robot activates it
        async for _progress in drone.ftp.upload(str(policy_file), "/policies"):
            pass
        assert await drone.ftp.are_files_identical(str(policy_file), "/policies/paper10_cell.qtab")
        await drone.ftp.rename("/policies/paper10_cell.qtab", "/policies/active.qtab")
        assert await drone.param.get_param_int("POLICY_CRC_LO") == policy.crc & 0xFFFF
        assert await drone.param.get_param_int("POLICY_CRC_HI") == (policy.crc >> 16) & 0xFFFF
        # flight mode named, arming with live sensors (the sim feeds them)
        assert str(await first(drone.telemetry.flight_mode())) == "HOLD"
        await drone.action.arm()
        assert await first(drone.telemetry.armed())
        # AUTO and GUIDED as MAVSDK's ArduPilot Rover table names them: Auto (10) is MISSION,
        # Guided (15) is OFFBOARD; a mission of targets A and D, MAVSDK's own start and go-to
        home = await first(drone.telemetry.home())
        lat0, lon0 = round(home.latitude_deg * 1e7), round(home.longitude_deg * 1e7)
        a, d = (frames.world_to_global(*cell_world_mm(c, r), lat0, lon0) for c, r in ((2, 2), (9, 7)))
        await drone.mission_raw.upload_mission([
            MissionItem(i, mavsdk_frame, 16, int(i == 0), 1, 0, 0, 0, float("nan"), lat, lon, 0.0, 0)
            for i, (lat, lon) in enumerate((a, d))])
        await drone.mission_raw.start_mission()  # DO_SET_MODE Auto, then MISSION_START
        assert await mode_becomes(drone, "MISSION")
        await drone.action.goto_location(d[0] / 1e7, d[1] / 1e7, 0.0, float("nan"))
        assert await mode_becomes(drone, "OFFBOARD")
        await drone.action.hold()
        assert await mode_becomes(drone, "HOLD")
        await drone.action.disarm()

    try:
        asyncio.run(asyncio.wait_for(scenario(), 180))
    finally:
        assert sitl.stop(signal.SIGINT) == 0, "\n".join(sitl.log[-20:])


@pytest.mark.timeout(300)
@pytest.mark.wallclock  # `qnav sitl` in real time and MAVSDK's own FTP/command timeouts
def test_mavsdk_with_a_generic_autopilot_shows_why_the_option_exists(tmp_path):
    mavsdk = mavsdk_or_skip()
    sitl = SitlProcess(tmp_path, "--policy", "none")

    async def scenario() -> None:
        drone = await connected(mavsdk, mavsdk_url(sitl))
        assert str(await first(drone.telemetry.flight_mode())) == "UNKNOWN"
        raw = await drone.param.get_param_int("GOAL_TOL_MM")
        import struct

        # bytewise decoding of the C-cast value: the float bits of 150.0
        assert raw == struct.unpack("<i", struct.pack("<f", float(robot_spec.GOAL_TOLERANCE_MM)))[0]

    try:
        asyncio.run(asyncio.wait_for(scenario(), 120))
    finally:
        assert sitl.stop(signal.SIGINT) == 0, "\n".join(sitl.log[-20:])
