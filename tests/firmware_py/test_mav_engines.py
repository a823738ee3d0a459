"""MAVLink node engines driven directly: params, commands, missions,
telemetry, signing and GCS failsafe, through real MAVLink frames (every
message is packed to bytes and parsed back, both directions)."""

from __future__ import annotations

import hashlib
import json
import math

import pytest

from firmware_py import robot_spec
from firmware_py.mavlink import frames as mav_frames
from firmware_py.mavlink.dialect import mavlink2 as m
from firmware_py.mavlink.node import MavNode
from firmware_py.mavlink.params import PARAMS, ParamStore, as_float32
from firmware_py.mavlink.signing import Signing, load_key_file
from firmware_py.vehicle import CtrlState, Mode
from tests.support.mav_vehicle import TestVehicle

GCS = (255, 190)
KEY = hashlib.sha256(b"qnav test key").digest()


class Link:
    """A GCS codec and the robot node, joined by bytes."""

    def __init__(self, tmp_path=None, key: bytes | None = None, boot_key_file=None):
        self.vehicle = TestVehicle()
        self.storage = tmp_path
        self.node = MavNode(self.vehicle, ParamStore(tmp_path), Signing(tmp_path))
        self.now = 1_000_000
        self.node.boot(self.now, boot_key_file)
        self.gcs = m.MAVLink(None, *GCS)
        if key is not None:
            self.gcs.signing.secret_key = key
            self.gcs.signing.sign_outgoing = True
            self.gcs.signing.link_id = 1
            self.gcs.signing.timestamp = self.node.signing.timestamp + 10
        self._robot_codec = m.MAVLink(None, 1, 1)
        self._decoder = m.MAVLink(None)

    def frame(self, msg) -> bytes:
        return bytes(msg.pack(self.gcs))

    def feed(self, data: bytes) -> list:
        msg = m.MAVLink(None).parse_char(data)
        replies = self.node.handle(msg, self.now)
        return [self._decoder.parse_char(bytes(r.pack(self._robot_codec))) for r in replies]

    def send(self, msg) -> list:
        return self.feed(self.frame(msg))

    def tick(self, dt_us: int = 0) -> list:
        self.now += dt_us
        return [self._decoder.parse_char(bytes(r.pack(self._robot_codec))) for r in self.node.tick(self.now)]

    def cmd(self, command: int, *p: float):
        p = list(p) + [0.0] * (7 - len(p))
        return self.send(self.gcs.command_long_encode(1, 1, command, 0, *p))


def of(msgs, kind):
    return [x for x in msgs if x.get_type() == kind]


def ack(msgs):
    (a,) = of(msgs, "COMMAND_ACK")
    return a.result


def texts(msgs):
    return [x.text for x in of(msgs, "STATUSTEXT")]


# --- parameters -----------------------------------------------------------------------------

def test_param_list_read_and_set_persist(tmp_path):
    link = Link(tmp_path)
    values = of(link.send(link.gcs.param_request_list_encode(1, 1)), "PARAM_VALUE")
    assert [v.param_id for v in values] == [p.name for p in PARAMS]
    assert all(v.param_count == len(PARAMS) and v.param_index == i for i, v in enumerate(values))
    assert {v.param_id: v.param_value for v in values}["FS_GCS_TOUT_MS"] == 5000

    (pv,) = link.send(link.gcs.param_set_encode(1, 1, b"FS_GCS_TOUT_MS", 2500, 6))
    assert (pv.param_id, pv.param_value) == ("FS_GCS_TOUT_MS", 2500)
    assert link.vehicle.cfg.gcs_timeout_ms == 2500  # applied to the vehicle at once
    assert json.loads((tmp_path / "params" / "params.json").read_text())["params"]["FS_GCS_TOUT_MS"] == 2500

    (pv,) = link.send(link.gcs.param_request_read_encode(1, 1, b"", link.node.params.index("GOAL_TOL_MM")))
    assert pv.param_id == "GOAL_TOL_MM" and pv.param_value == robot_spec.GOAL_TOLERANCE_MM

    # a fresh boot from the same storage sees the stored value
    again = Link(tmp_path)
    assert again.node.params.get("FS_GCS_TOUT_MS") == 2500 and again.vehicle.cfg.gcs_timeout_ms == 2500


def test_out_of_range_set_keeps_value_and_says_why_also_after_reboot(tmp_path):
    link = Link(tmp_path)
    link.send(link.gcs.param_set_encode(1, 1, b"SPEED_SCALE", 80, 6))
    replies = link.send(link.gcs.param_set_encode(1, 1, b"SPEED_SCALE", 500, 6))
    (pv,) = of(replies, "PARAM_VALUE")
    assert pv.param_value == 80
    assert any("out of range" in t and "SPEED_SCALE" in t for t in texts(replies))
    replies = link.send(link.gcs.param_set_encode(1, 1, b"SPEED_SCALE", 50.5, 6))
    assert of(replies, "PARAM_VALUE")[0].param_value == 80 and "integer" in texts(replies)[0]
    assert ack(link.cmd(m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)) == m.MAV_RESULT_ACCEPTED
    assert link.node.reboots == 1 and link.node.params.get("SPEED_SCALE") == 80
    assert Link(tmp_path).node.params.get("SPEED_SCALE") == 80


def test_unknown_and_readonly_params_are_refused(tmp_path):
    link = Link(tmp_path)
    assert "unknown parameter NOPE" in texts(link.send(link.gcs.param_set_encode(1, 1, b"NOPE", 1, 6)))
    link.vehicle.st.policy_id, link.vehicle.st.policy_crc = 7, 0xDEADBEEF
    replies = link.send(link.gcs.param_set_encode(1, 1, b"POLICY_ID", 3, 6))
    assert "read-only" in texts(replies)[0] and of(replies, "PARAM_VALUE")[0].param_value == 7
    values = {v.param_id: v.param_value for v in of(link.send(link.gcs.param_request_list_encode(1, 1)), "PARAM_VALUE")}
    assert (int(values["POLICY_CRC_HI"]) << 16 | int(values["POLICY_CRC_LO"])) == 0xDEADBEEF
    assert values["POLICY_CRC"] == as_float32(0xDEADBEEF)


def test_corrupt_param_file_means_defaults_and_a_statustext(tmp_path):
    (tmp_path / "params").mkdir()
    (tmp_path / "params" / "params.json").write_text("{ not json")
    link = Link(tmp_path)
    assert link.node.params.get("SPEED_SCALE") == 100
    assert any("corrupt" in t for t in texts(link.tick()))
    (tmp_path / "params" / "params.json").write_text(json.dumps({"version": 1, "params": {"SPEED_SCALE": 5, "BOGUS": 1,
                                                                                "GOAL_TOL_MM": 300}}))
    link = Link(tmp_path)
    assert link.node.params.get("GOAL_TOL_MM") == 300 and link.node.params.get("SPEED_SCALE") == 100
    warnings = texts(link.tick())
    assert any("SPEED_SCALE" in t for t in warnings) and any("BOGUS" in t for t in warnings)


def test_param_file_write_is_atomic(tmp_path, monkeypatch):
    store = ParamStore(tmp_path)
    assert store.set("SPEED_SCALE", 70)[0]
    import firmware_py.mavlink.params as params_mod

    def crash(*_):
        raise OSError("disk full")
    monkeypatch.setattr(params_mod.os, "replace", crash)
    assert store.set("SPEED_SCALE", 60)[0]  # in effect; the failed save is kept for the GCS, not raised
    assert store.save_errors == 1 and "disk full" in (store.pop_save_failure() or "")
    fresh = ParamStore(tmp_path)
    assert fresh.load() == [] and fresh.get("SPEED_SCALE") == 70  # old file intact


# --- commands ------------------------------------------------------------------------------------

def test_arm_disarm_mode_and_refusals():
    link = Link()
    assert ack(link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)) == m.MAV_RESULT_ACCEPTED
    assert link.vehicle.st.armed
    hb = of(link.send(link.gcs.command_long_encode(1, 1, m.MAV_CMD_REQUEST_MESSAGE, 0, 0, 0, 0, 0, 0, 0, 0)),
            "HEARTBEAT")[0]
    assert hb.base_mode & m.MAV_MODE_FLAG_SAFETY_ARMED and hb.type == m.MAV_TYPE_GROUND_ROVER
    assert hb.autopilot == m.MAV_AUTOPILOT_GENERIC and hb.system_status == m.MAV_STATE_ACTIVE

    assert ack(link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)) == m.MAV_RESULT_ACCEPTED
    assert link.vehicle.st.mode == Mode.GUIDED
    replies = link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.AUTO)
    assert ack(replies) == m.MAV_RESULT_DENIED and "no mission" in texts(replies)[0]
    assert ack(link.cmd(m.MAV_CMD_DO_SET_MODE, 1, 99)) == m.MAV_RESULT_DENIED
    assert ack(link.cmd(m.MAV_CMD_DO_SET_MODE, 0, Mode.HOLD)) == m.MAV_RESULT_DENIED  # no custom flag
    # legacy SET_MODE is answered with a DO_SET_MODE ack
    replies = link.send(link.gcs.set_mode_encode(1, 1, Mode.HOLD))
    assert of(replies, "COMMAND_ACK")[0].command == m.MAV_CMD_DO_SET_MODE and link.vehicle.st.mode == Mode.HOLD

    replies = link.cmd(m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
    assert ack(replies) == m.MAV_RESULT_TEMPORARILY_REJECTED and "disarm first" in texts(replies)[0]
    assert ack(link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 0)) == m.MAV_RESULT_ACCEPTED
    link.vehicle.refuse_arm = "sensors stale"
    replies = link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert ack(replies) == m.MAV_RESULT_DENIED and texts(replies) == ["arm refused: sensors stale"]
    assert ack(link.cmd(m.MAV_CMD_NAV_TAKEOFF)) == m.MAV_RESULT_UNSUPPORTED
    # COMMAND_INT goes through the same table; a command for another system is ignored
    replies = link.send(link.gcs.command_int_encode(1, 1, 0, m.MAV_CMD_DO_SET_MODE, 0, 0, 1, Mode.GUIDED,
                                                    0, 0, 0, 0, 0))
    assert ack(replies) == m.MAV_RESULT_ACCEPTED
    assert link.send(link.gcs.command_long_encode(9, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)) == []


def test_message_interval_and_request_message():
    link = Link()
    link.tick()
    counts = {}
    for _ in range(40):  # 2 s in 50 ms ticks
        for x in link.tick(50_000):
            counts[x.get_type()] = counts.get(x.get_type(), 0) + 1
    assert counts["HEARTBEAT"] == 2 and counts["LOCAL_POSITION_NED"] == 10  # 1 Hz, TELEM_POS_HZ=5
    assert ack(link.cmd(m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_HEARTBEAT, 100_000)) == m.MAV_RESULT_ACCEPTED
    assert ack(link.cmd(m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_ATTITUDE, -1)) == m.MAV_RESULT_ACCEPTED
    counts = {}
    for _ in range(20):
        for x in link.tick(50_000):
            counts[x.get_type()] = counts.get(x.get_type(), 0) + 1
    assert counts["HEARTBEAT"] == 10 and "ATTITUDE" not in counts
    (mi,) = of(link.cmd(m.MAV_CMD_GET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_HEARTBEAT), "MESSAGE_INTERVAL")
    assert mi.interval_us == 100_000
    assert ack(link.cmd(m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_HEARTBEAT, 0)) == m.MAV_RESULT_ACCEPTED
    assert link.node.telemetry.interval_us(m.MAVLINK_MSG_ID_HEARTBEAT) == 1_000_000
    assert ack(link.cmd(m.MAV_CMD_SET_MESSAGE_INTERVAL, 9999, 100_000)) == m.MAV_RESULT_DENIED
    replies = link.cmd(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert ack(replies) == m.MAV_RESULT_ACCEPTED
    assert of(replies, "AUTOPILOT_VERSION")[0].capabilities & m.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    assert ack(link.cmd(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_SCALED_IMU)) == m.MAV_RESULT_DENIED


def test_telemetry_frames_match_the_world_frame():
    link = Link()
    st = link.vehicle.st
    st.x_mm, st.y_mm, st.heading_mrad, st.speed_mm_s = 3000, 1000, 1571, 200  # facing north
    st.ranges_mm = [500, 2500, 800, 0, 0, 0, 0, 0]
    st.range_status = [robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_FAR, robot_spec.RANGE_VALID] + [robot_spec.RANGE_INVALID] * 5
    get = {}
    for msg_id in (m.MAVLINK_MSG_ID_LOCAL_POSITION_NED, m.MAVLINK_MSG_ID_ATTITUDE,
                   m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, m.MAVLINK_MSG_ID_OBSTACLE_DISTANCE,
                   m.MAVLINK_MSG_ID_HOME_POSITION, m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN):
        replies = link.cmd(m.MAV_CMD_REQUEST_MESSAGE, msg_id)
        get[msg_id] = [x for x in replies if x.get_type() not in ("COMMAND_ACK",)][0]
    lp = get[m.MAVLINK_MSG_ID_LOCAL_POSITION_NED]
    assert (lp.x, lp.y) == pytest.approx((1.0, 3.0)) and lp.vx == pytest.approx(0.2, abs=1e-3)
    assert get[m.MAVLINK_MSG_ID_ATTITUDE].yaw == pytest.approx(0.0, abs=1e-3)  # north
    gp = get[m.MAVLINK_MSG_ID_GLOBAL_POSITION_INT]
    lat0, lon0 = link.node.params.get("ORIGIN_LAT"), link.node.params.get("ORIGIN_LON")
    north_m = (gp.lat - lat0) * mav_frames.M_PER_E7
    east_m = (gp.lon - lon0) * mav_frames.M_PER_E7 * math.cos(math.radians(lat0 * 1e-7))
    assert (north_m, east_m) == pytest.approx((1.0, 3.0), abs=0.01)
    assert get[m.MAVLINK_MSG_ID_HOME_POSITION].latitude == lat0
    assert get[m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN].longitude == lon0
    od = get[m.MAVLINK_MSG_ID_OBSTACLE_DISTANCE]
    assert od.frame == m.MAV_FRAME_BODY_FRD and od.increment == 5
    assert od.distances[0] == 50  # nose sensor, cm
    assert od.distances[(360 - 45) // 5] == od.max_distance + 1  # CCW 45 deg sensor = FRD 315, too far
    assert od.distances[(360 - 90) // 5] == 80
    assert od.distances[180 // 5] == 0xFFFF  # invalid reading -> unknown


def test_failsafe_events_and_heartbeat_state():
    link = Link()
    link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)
    link.tick()
    link.tick(10_000_000)  # no GCS heartbeat ever: no failsafe (ArduPilot behaviour)
    assert not link.node.failsafe
    link.send(link.gcs.heartbeat_encode(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0))
    t_last = link.now
    period = robot_spec.CONTROL_PERIOD_US
    while not link.node.failsafe:
        out = link.tick(period)
        assert link.now <= t_last + 5_000_000 + period
    assert link.now > t_last + 5_000_000
    assert any(t.startswith("GCS failsafe") for t in texts(out))
    assert link.vehicle.st.mode == Mode.HOLD and link.vehicle.failsafe_calls == [True]
    hb = link.node.telemetry.heartbeat(link.vehicle.status())
    assert hb.system_status == m.MAV_STATE_CRITICAL
    replies = link.send(link.gcs.heartbeat_encode(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0))
    assert "GCS failsafe cleared" in texts(replies) and link.vehicle.failsafe_calls == [True, False]
    # a non-GCS heartbeat (another vehicle) does not feed the failsafe
    link.send(link.gcs.heartbeat_encode(m.MAV_TYPE_GROUND_ROVER, m.MAV_AUTOPILOT_GENERIC, 0, 0, 0))
    link.tick(5_100_000)
    assert link.node.failsafe


def test_control_inputs_from_the_failsafes_gcs_keep_it_alive_once_it_watches():
    """A command from SYSID_MYGCS that the robot accepts (arm, mode) between two monitors counts as that
    GCS's heartbeat; before any GCS heartbeat it starts no watch, another system's commands and refused
    ones feed nothing, and it does not clear a failsafe (a heartbeat does)."""
    link = Link()
    period = robot_spec.CONTROL_PERIOD_US
    link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    link.tick(10_000_000)
    assert link.node.gcs_last_heartbeat_us is None and not link.node.failsafe  # no watch from commands
    link.send(link.gcs.heartbeat_encode(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0))
    for _ in range(3):  # 3 x 4 s, commands only: never 5 s without the GCS
        link.tick(4_000_000)
        assert ack(link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)) == m.MAV_RESULT_ACCEPTED
        assert not link.node.failsafe
    link.node.params.set("SYSID_MYGCS", 255)
    other = m.MAVLink(None, 77, 190)  # SYSID_MYGCS refuses it: its commands keep nothing alive
    t_last = link.now
    while not link.node.failsafe:
        link.feed(bytes(other.command_long_encode(1, 1, m.MAV_CMD_DO_SET_MODE, 0, 1, Mode.GUIDED, 0, 0, 0, 0, 0)
                        .pack(other)))
        link.tick(period)
    assert t_last + 5_000_000 < link.now <= t_last + 5_000_000 + period
    assert ack(link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)) == m.MAV_RESULT_DENIED  # held by the failsafe
    assert link.node.failsafe
    link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.HOLD)
    assert link.node.failsafe
    replies = link.send(link.gcs.heartbeat_encode(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0))
    assert "GCS failsafe cleared" in texts(replies)


# --- missions --------------------------------------------------------------------------------------

def upload(link, items, *, as_int=True, drop_first=False):
    """Answer the robot's requests like a GCS; returns the final MISSION_ACK."""
    replies = link.send(link.gcs.mission_count_encode(1, 1, len(items), 0))
    dropped = False
    while True:
        req = of(replies, "MISSION_REQUEST_INT")
        acks = of(replies, "MISSION_ACK")
        if acks:
            return acks[0], replies
        (req,) = req
        if drop_first and not dropped:  # the item is lost: the robot must ask again
            dropped = True
            replies = link.tick(link.node.params.get("MIS_TIMEOUT_MS") * 1000)
            continue
        frame, x, y = items[req.seq]
        if as_int:
            msg = link.gcs.mission_item_int_encode(1, 1, req.seq, frame, m.MAV_CMD_NAV_WAYPOINT, 0, 1,
                                                   0, 0, 0, 0, x, y, 0, 0)
        else:
            msg = link.gcs.mission_item_encode(1, 1, req.seq, frame, m.MAV_CMD_NAV_WAYPOINT, 0, 1,
                                               0, 0, 0, 0, x, y, 0, 0)
        replies = link.send(msg)


def test_mission_upload_local_and_global_frames_convert_to_world():
    link = Link()
    lat0, lon0 = link.node.params.get("ORIGIN_LAT"), link.node.params.get("ORIGIN_LON")
    lat, lon = mav_frames.world_to_global(4000, -2000, lat0, lon0)
    items = [(m.MAV_FRAME_LOCAL_NED, 25_000, 10_000),  # 2.5 m north, 1 m east (1e4 scaling)
             (m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, lat, lon)]
    a, replies = upload(link, items, drop_first=True)
    assert a.type == m.MAV_MISSION_ACCEPTED
    assert link.vehicle.mission[0] == (1000, 2500)
    assert link.vehicle.mission[1] == pytest.approx((4000, -2000), abs=12)  # 1e-7 deg ~ 11 mm
    # float MISSION_ITEM in metres works too
    a, _ = upload(link, [(m.MAV_FRAME_LOCAL_NED, 1.5, -0.5)], as_int=False)
    assert a.type == m.MAV_MISSION_ACCEPTED and link.vehicle.mission == [(-500, 1500)]


def test_mission_download_returns_what_was_uploaded():
    link = Link()
    items = [(m.MAV_FRAME_LOCAL_NED, 10_000 * i, -5_000 * i) for i in range(4)]
    assert upload(link, items)[0].type == m.MAV_MISSION_ACCEPTED
    (count,) = of(link.send(link.gcs.mission_request_list_encode(1, 1, 0)), "MISSION_COUNT")
    assert count.count == 4
    got = []
    for seq in range(4):
        (it,) = of(link.send(link.gcs.mission_request_int_encode(1, 1, seq, 0)), "MISSION_ITEM_INT")
        got.append((it.frame, it.x, it.y))
    assert got == items
    assert link.send(link.gcs.mission_ack_encode(1, 1, 0, 0)) == []
    (bad,) = of(link.send(link.gcs.mission_request_int_encode(1, 1, 9, 0)), "MISSION_ACK")
    assert bad.type == m.MAV_MISSION_INVALID_SEQUENCE


def test_mission_errors_timeout_clear_and_set_current():
    link = Link()
    upload(link, [(m.MAV_FRAME_LOCAL_NED, 0, 10_000)])
    old = list(link.vehicle.mission)
    # unsupported command
    link.send(link.gcs.mission_count_encode(1, 1, 1, 0))
    replies = link.send(link.gcs.mission_item_int_encode(1, 1, 0, m.MAV_FRAME_LOCAL_NED, m.MAV_CMD_NAV_LAND,
                                                         0, 1, 0, 0, 0, 0, 0, 0, 0, 0))
    assert of(replies, "MISSION_ACK")[0].type == m.MAV_MISSION_UNSUPPORTED and link.vehicle.mission == old
    # unsupported frame
    link.send(link.gcs.mission_count_encode(1, 1, 1, 0))
    replies = link.send(link.gcs.mission_item_int_encode(1, 1, 0, m.MAV_FRAME_BODY_FRD, m.MAV_CMD_NAV_WAYPOINT,
                                                         0, 1, 0, 0, 0, 0, 0, 0, 0, 0))
    assert of(replies, "MISSION_ACK")[0].type == m.MAV_MISSION_UNSUPPORTED_FRAME
    # the GCS goes silent: requests repeat MIS_RETRIES times, then the upload is cancelled
    requests = of(link.send(link.gcs.mission_count_encode(1, 1, 2, 0)), "MISSION_REQUEST_INT")
    timeout = link.node.params.get("MIS_TIMEOUT_MS") * 1000
    final = []
    for _ in range(10):
        out = link.tick(timeout)
        requests += of(out, "MISSION_REQUEST_INT")
        final += of(out, "MISSION_ACK")
    assert len(requests) == 1 + link.node.params.get("MIS_RETRIES")
    assert [a.type for a in final] == [m.MAV_MISSION_OPERATION_CANCELLED] and link.vehicle.mission == old
    # fence uploads are not supported
    (a,) = of(link.send(link.gcs.mission_count_encode(1, 1, 3, m.MAV_MISSION_TYPE_FENCE)), "MISSION_ACK")
    assert a.type == m.MAV_MISSION_UNSUPPORTED
    upload(link, [(m.MAV_FRAME_LOCAL_NED, 0, 10_000), (m.MAV_FRAME_LOCAL_NED, 0, 20_000)])
    (cur,) = of(link.send(link.gcs.mission_set_current_encode(1, 1, 1)), "MISSION_CURRENT")
    assert cur.seq == 1 and link.vehicle.st.mission_seq == 1
    (a,) = of(link.send(link.gcs.mission_clear_all_encode(1, 1, 0)), "MISSION_ACK")
    assert a.type == m.MAV_MISSION_ACCEPTED and link.vehicle.mission == [] and link.node.mission.items == []


def test_auto_mission_runs_and_reports_items_reached():
    link = Link()
    wps = [(m.MAV_FRAME_LOCAL_NED, 10_000, 0), (m.MAV_FRAME_LOCAL_NED, 10_000, 10_000)]
    upload(link, wps)
    assert ack(link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)) == m.MAV_RESULT_ACCEPTED
    assert ack(link.cmd(m.MAV_CMD_MISSION_START)) == m.MAV_RESULT_ACCEPTED
    reached, current = [], []
    for _ in range(200):
        link.vehicle.step(50_000)
        out = link.tick(50_000)
        reached += [x.seq for x in of(out, "MISSION_ITEM_REACHED")]
        current += of(out, "MISSION_CURRENT")
    assert reached == [0, 1]
    assert current[-1].mission_state == m.MISSION_STATE_COMPLETE
    assert link.vehicle.st.state == CtrlState.HOLD


def test_guided_goal_echo_and_refusal():
    link = Link()
    goal = link.gcs.set_position_target_local_ned_encode(0, 1, 1, m.MAV_FRAME_LOCAL_NED, 0xFFF8,
                                                          2.0, 1.0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    assert "goal refused: not in Guided" in texts(link.send(goal))
    link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)
    (echo,) = of(link.send(goal), "POSITION_TARGET_LOCAL_NED")
    assert (echo.x, echo.y) == pytest.approx((2.0, 1.0)) and link.vehicle.st.goal_mm == (1000, 2000)


# --- signing ------------------------------------------------------------------------------------------

def test_signing_drops_unsigned_bad_and_replayed(tmp_path):
    key_file = tmp_path / "key.txt"
    key_file.write_text("qnav test key\n")
    assert load_key_file(key_file) == KEY
    link = Link(tmp_path, key=KEY, boot_key_file=key_file)
    arm = link.gcs.command_long_encode(1, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    # unsigned ARM: ignored, counted
    unsigned = m.MAVLink(None, *GCS)
    assert link.feed(bytes(arm.pack(unsigned))) == [] and not link.vehicle.st.armed
    assert link.node.signing.dropped_unsigned == 1
    # wrong key
    other = m.MAVLink(None, *GCS)
    other.signing.secret_key, other.signing.sign_outgoing = b"x" * 32, True
    other.signing.timestamp = link.node.signing.timestamp + 5
    assert link.feed(bytes(link.gcs.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(other))) == []
    assert link.node.signing.dropped_badsig == 1 and not link.vehicle.st.armed
    # signed ARM works; replaying the captured frame after a DISARM is dropped
    signed_arm = link.frame(arm)
    assert ack(link.feed(signed_arm)) == m.MAV_RESULT_ACCEPTED and link.vehicle.st.armed
    assert ack(link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 0)) == m.MAV_RESULT_ACCEPTED
    assert link.feed(signed_arm) == [] and not link.vehicle.st.armed
    assert link.node.signing.dropped_replay == 1
    # RADIO_STATUS may come unsigned (radios cannot sign)
    radio = m.MAVLink(None, 3, 68).radio_status_encode(200, 190, 90, 80, 70, 0, 0)
    link.feed(bytes(radio.pack(m.MAVLink(None, 3, 68))))
    assert link.node.signing.accepted_unsigned == 1
    # SYS_STATUS reports the drops
    (sys_status,) = of(link.cmd(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_SYS_STATUS), "SYS_STATUS")
    assert sys_status.errors_count3 == 3 and sys_status.errors_comm == 3
    # after a reboot (fresh node on the same storage) the replay is still refused
    link.node.signing.persist()
    again = Link(tmp_path, key=KEY, boot_key_file=key_file)
    assert again.feed(signed_arm) == [] and again.node.signing.dropped_replay == 1
    assert again.node.signing.timestamp >= link.node.signing.timestamp


def test_setup_signing_provisions_persists_and_disables(tmp_path):
    link = Link(tmp_path)
    assert link.node.params.set("SIGN_NET_SETUP", 1)[0]  # the operator allows it on the robot
    replies = link.send(link.gcs.setup_signing_encode(1, 1, list(KEY), link.node.signing.timestamp))
    assert texts(replies) == ["signing key set"]
    assert json.loads((tmp_path / "params" / "signing.json").read_text())["key"] == KEY.hex()
    # now unsigned commands are ignored...
    assert link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1) == [] and not link.vehicle.st.armed
    # ...a rebooted robot still has the key...
    signed = Link(tmp_path, key=KEY)
    assert signed.node.signing.key == KEY
    assert ack(signed.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)) == m.MAV_RESULT_ACCEPTED
    # ...and a signed all-zero SETUP_SIGNING turns signing off
    assert texts(signed.send(signed.gcs.setup_signing_encode(1, 1, [0] * 32, 0))) == ["signing disabled"]
    assert signed.node.signing.key is None
    plain = m.MAVLink(None, *GCS)
    msg = plain.command_long_encode(1, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 0, 0, 0, 0, 0)
    assert ack(signed.feed(bytes(msg.pack(plain)))) == m.MAV_RESULT_ACCEPTED


def test_corrupt_signing_state_resets_with_warning(tmp_path):
    (tmp_path / "params").mkdir()
    (tmp_path / "params" / "signing.json").write_text("garbage")
    link = Link(tmp_path)
    assert link.node.signing.key is None
    assert any("signing state corrupt" in t for t in texts(link.tick()))


def test_ftp_is_routed_to_the_ftp_server_and_always_needs_a_signature_with_a_key(tmp_path):
    from firmware_py.mavlink.ftp_server import HEADER, FtpServer, Op
    from firmware_py.storage import Storage

    server = FtpServer(Storage(tmp_path))
    link = Link(tmp_path)
    link.node.ftp = server
    (tmp_path / "hello.txt").write_bytes(b"hi robot")
    path = b"/hello.txt"
    req = HEADER.pack(7, 0, Op.OPEN_FILE_RO, len(path), 0, 0, 0, 0) + path
    (reply,) = of(link.send(link.gcs.file_transfer_protocol_encode(0, 1, 1, list(req.ljust(251, b"\0")))),
                  "FILE_TRANSFER_PROTOCOL")
    assert (reply.target_system, reply.target_component) == GCS
    seq, _session, opcode, size, req_op, *_ = HEADER.unpack_from(bytes(reply.payload))
    assert (seq, opcode, req_op, size) == (8, Op.ACK, Op.OPEN_FILE_RO, 4)
    assert int.from_bytes(bytes(reply.payload)[12:16], "little") == 8  # file size
    # with a key and SIGN_REQUIRE=0, unsigned commands pass but unsigned FTP does not
    signed = Link(tmp_path, key=KEY)
    signed.node.ftp = server
    signed.node.params.set("SIGN_NET_SETUP", 1)
    signed.send(signed.gcs.setup_signing_encode(1, 1, list(KEY), signed.node.signing.timestamp))
    assert of(signed.send(signed.gcs.param_set_encode(1, 1, b"SIGN_REQUIRE", 0, 6)), "PARAM_VALUE")[0].param_value == 0
    plain = m.MAVLink(None, *GCS)
    arm = plain.command_long_encode(1, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    assert ack(signed.feed(bytes(arm.pack(plain)))) == m.MAV_RESULT_ACCEPTED
    ftp = plain.file_transfer_protocol_encode(0, 1, 1, list(req.ljust(251, b"\0")))
    assert signed.feed(bytes(ftp.pack(plain))) == []
    assert of(signed.send(ftp), "FILE_TRANSFER_PROTOCOL")


def test_docs_parameter_table_matches_the_code():
    import pathlib

    doc = (pathlib.Path(__file__).resolve().parents[2] / "docs" / "mavlink.md").read_text()
    rows = {}
    for line in doc.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 6 and cells[0].startswith("`") and cells[0].strip("`").isupper():
            rows[cells[0].strip("`")] = cells
    assert list(rows) == [p.name for p in PARAMS]
    for p in PARAMS:
        _, default, lo, hi, drives, _ = rows[p.name]
        assert (int(default), int(lo), int(hi)) == (p.default, p.min, p.max), p.name
        assert (p.field or "") in drives.strip("`") or (not p.field and drives.startswith(("node", "read")))
