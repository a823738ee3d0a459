"""Issue 30's ground-station conventions on the robot's MAVLink node: VFR_HUD
streamed (ground speed, compass heading) and an AUTOPILOT_VERSION uid that is the robot's own and survives a reboot."""

from __future__ import annotations

from firmware_py.mavlink.dialect import mavlink2 as m
from firmware_py.storage import UID_FILE
from tests.firmware_py.test_mav_engines import Link, ack, of, texts


def test_vfr_hud_is_streamed_with_speed_and_compass_heading():
    link = Link()
    link.vehicle.st.speed_mm_s = 250
    link.vehicle.st.heading_mrad = 0  # east in the world frame: compass 90
    huds = []
    for _ in range(30):
        huds += of(link.tick(100_000), "VFR_HUD")
    assert huds, "no VFR_HUD in 3 s"
    hud = huds[-1]
    assert abs(hud.groundspeed - 0.25) < 1e-6 and hud.heading == 90


def test_autopilot_version_uid_is_the_robots_own_and_survives_a_reboot(tmp_path):
    def uid(storage):
        link = Link(storage)
        (v,) = of(link.cmd(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_AUTOPILOT_VERSION), "AUTOPILOT_VERSION")
        return v.uid

    first = uid(tmp_path / "a")
    assert first != 0 and (tmp_path / "a" / UID_FILE.lstrip("/")).is_file()
    assert uid(tmp_path / "a") == first  # kept across boots
    assert uid(tmp_path / "b") not in (0, first)  # another robot, another id


def test_standard_modes_are_listed_streamed_and_set():
    """Issue 30: MAVLink's Standard Modes, what QGroundControl builds a generic autopilot's mode menu
    from: AVAILABLE_MODES lists the four modes (Hold = POSITION_HOLD, Auto = MISSION, Manual and Guided
    by name), CURRENT_MODE is streamed, DO_SET_STANDARD_MODE switches to a standard mode and refuses one
    the robot does not have with the list it has; the HEARTBEAT is unchanged (custom_mode)."""
    from firmware_py.vehicle import Mode

    link = Link()
    modes = of(link.cmd(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_AVAILABLE_MODES), "AVAILABLE_MODES")
    assert [(x.mode_index, x.number_modes) for x in modes] == [(1, 4), (2, 4), (3, 4), (4, 4)]
    table = {x.custom_mode: (x.standard_mode, x.mode_name) for x in modes}
    assert table == {int(Mode.MANUAL): (m.MAV_STANDARD_MODE_NON_STANDARD, "Manual"),
                     int(Mode.HOLD): (m.MAV_STANDARD_MODE_POSITION_HOLD, ""),
                     int(Mode.AUTO): (m.MAV_STANDARD_MODE_MISSION, ""),
                     int(Mode.GUIDED): (m.MAV_STANDARD_MODE_NON_STANDARD, "Guided")}
    (one,) = of(link.cmd(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_AVAILABLE_MODES, 3), "AVAILABLE_MODES")
    assert one.mode_index == 3
    assert of(link.cmd(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_AVAILABLE_MODES_MONITOR),
              "AVAILABLE_MODES_MONITOR")[0].seq == 0
    current = [x for _ in range(15) for x in of(link.tick(100_000), "CURRENT_MODE")]
    assert current and (current[-1].standard_mode, current[-1].custom_mode) == (m.MAV_STANDARD_MODE_POSITION_HOLD,
                                                                                int(Mode.HOLD))
    link.vehicle.mission = [(1000, 1000)]  # Auto needs a mission on the test vehicle
    replies = link.cmd(m.MAV_CMD_DO_SET_STANDARD_MODE, m.MAV_STANDARD_MODE_MISSION)
    assert of(replies, "COMMAND_ACK")[0].result == m.MAV_RESULT_ACCEPTED and link.vehicle.st.mode == Mode.AUTO
    replies = link.cmd(m.MAV_CMD_DO_SET_STANDARD_MODE, m.MAV_STANDARD_MODE_ORBIT)
    assert of(replies, "COMMAND_ACK")[0].result == m.MAV_RESULT_DENIED and link.vehicle.st.mode == Mode.AUTO
    assert "standard mode 2 not available (available: 1 (Hold), 6 (Auto))" in "".join(texts(replies))  # 2 chunks
    (hb,) = of(link.node.telemetry.build(m.MAVLINK_MSG_ID_HEARTBEAT, link.now, link.vehicle.status(), link.node.stats),
               "HEARTBEAT")
    assert hb.custom_mode == int(Mode.AUTO)  # what MAVProxy reads, unchanged


def _raw_replies(link: Link, command: int, *p: float) -> list:
    """The node's replies to a COMMAND_LONG as message objects (the Link's decoder has no 300/397)."""
    p = tuple(p) + (0.0,) * (7 - len(p))
    msg = m.MAVLink(None).parse_char(link.frame(link.gcs.command_long_encode(1, 1, command, 0, *p)))
    return link.node.handle(msg, link.now)


def test_protocol_version_and_component_metadata_with_the_parameter_json(tmp_path):
    """Issue 30: PROTOCOL_VERSION on MAV_CMD_REQUEST_PROTOCOL_VERSION; COMPONENT_METADATA pointing at a
    general metadata file on the robot's FTP server, which points at the parameter metadata made from
    the parameter table (descriptions, units, ranges, defaults); both frames parse from bytes."""
    import json

    from firmware_py.mavlink import extra
    from firmware_py.mavlink.ftp_server import PROTECTED, FtpServer
    from firmware_py.mavlink.node import MavNode
    from firmware_py.mavlink.params import PARAMS, ParamStore
    from firmware_py.mavlink.signing import Signing
    from firmware_py.storage import Storage
    from firmware_py.vehicle import VehicleConfig

    link = Link()
    link.node = MavNode(link.vehicle, ParamStore(tmp_path), Signing(tmp_path), ftp=FtpServer(Storage(tmp_path)))
    link.node.boot(link.now)  # as qnav-robot's shell: with storage and its FTP server
    codec, parser = m.MAVLink(None, 1, 1), extra.module().MAVLink(None)
    replies = _raw_replies(link, m.MAV_CMD_REQUEST_PROTOCOL_VERSION)
    assert sorted(r.get_type() for r in replies) == ["COMMAND_ACK", "PROTOCOL_VERSION"]
    pv = parser.parse_char(bytes(of(replies, "PROTOCOL_VERSION")[0].pack(codec)))
    assert (pv.version, pv.min_version, pv.max_version) == (200, 200, 200)
    replies = _raw_replies(link, m.MAV_CMD_REQUEST_MESSAGE, 397)
    cm = parser.parse_char(bytes(of(replies, "COMPONENT_METADATA")[0].pack(codec)))
    assert cm.get_type() == "COMPONENT_METADATA" and cm.uri == "mftp:///metadata/general.json"
    storage = Storage(tmp_path)
    assert cm.file_crc == storage.crc32("/metadata/general.json") != 0
    general = json.loads((tmp_path / "metadata" / "general.json").read_text())
    (ptype,) = general["metadataTypes"]
    assert ptype["type"] == 1 and ptype["uri"] == "mftp:///metadata/parameters.json"
    assert ptype["fileCrc"] == storage.crc32("/metadata/parameters.json")
    params = {p["name"]: p for p in json.loads((tmp_path / "metadata" / "parameters.json").read_text())["parameters"]}
    assert set(params) == {p.name for p in PARAMS}
    tol = params["GOAL_TOL_MM"]
    assert (tol["units"], tol["min"], tol["max"], tol["default"]) == ("mm", 20, 2000, VehicleConfig().goal_tolerance_mm)
    assert "goal counts as reached" in tol["shortDesc"] and params["SYSID_THISMAV"]["rebootRequired"]
    assert {"/metadata/general.json", "/metadata/parameters.json"} <= PROTECTED  # not writable over FTP
    no_storage = Link(tmp_path / "other")  # storage, but no FTP server to serve it from
    assert of([x for x in _raw_replies(no_storage, m.MAV_CMD_REQUEST_MESSAGE, 397)], "COMMAND_ACK")[0].result == \
        m.MAV_RESULT_DENIED


def test_rc_channels_override_drives_manual_as_for_ardupilot_rover():
    """MAVProxy's `rc` command and joystick module send RC_CHANNELS_OVERRIDE: channel 3 throttle,
    channel 1 steering (1100..1900 us, 1500 neutral) become Manual's sticks; released channels are
    no sample (the deadman stops the wheels)."""
    from firmware_py.mavlink.node import sticks_of_rc

    assert sticks_of_rc(1500, 1700) == (500, 0) and sticks_of_rc(1900, 1100) == (-1000, 1000)
    assert sticks_of_rc(2200, 1500) == (0, 1000)  # beyond the span: clamped
    assert sticks_of_rc(0, 0) is None and sticks_of_rc(0xFFFF, 0xFFFF) is None
    link = Link()
    seen = []
    link.vehicle.manual_control = lambda x, r, now_us: seen.append((x, r)) or True  # type: ignore[method-assign]
    link.send(link.gcs.rc_channels_override_encode(1, 1, 1500, 0, 1700, 0, 0, 0, 0, 0))
    link.send(link.gcs.rc_channels_override_encode(7, 1, 1500, 0, 1700, 0, 0, 0, 0, 0))  # another system's
    assert seen == [(500, 0)]


def test_get_home_position_answers_home_position_as_request_message_does():
    """MAV_CMD_GET_HOME_POSITION (deprecated, still sent by MAVProxy and older ground stations) is
    answered like REQUEST_MESSAGE(HOME_POSITION): ACCEPTED and the origin, from any system (it only
    asks for data, like the other read-only commands)."""
    link = Link()
    got = link.cmd(m.MAV_CMD_GET_HOME_POSITION)
    assert ack(got) == m.MAV_RESULT_ACCEPTED
    (home,) = of(got, "HOME_POSITION")
    (asked,) = of(link.cmd(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_HOME_POSITION), "HOME_POSITION")
    assert (home.latitude, home.longitude, home.altitude) == (asked.latitude, asked.longitude, asked.altitude)
