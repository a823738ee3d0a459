"""The holes hostile testing found in the MAVLink engines (issue 13), driven
directly: malformed mission items, handler exceptions, signing timestamps
near 2^48, unsigned SETUP_SIGNING over a network, replay after a crash,
foreign GCS heartbeats, and the FTP server's sessions and quotas."""

from __future__ import annotations

import json
import math
import os

import pytest

from firmware_py import robot_spec
from firmware_py.mavlink.dialect import mavlink2 as m
from firmware_py.mavlink.ftp_server import FtpServer, Nak, Op
from firmware_py.mavlink.node import is_network_url
from firmware_py.mavlink.signing import FUTURE_WINDOW, MAX_TIMESTAMP, wall_timestamp
from firmware_py.storage import LAYOUT_DIRS, Storage
from firmware_py.vehicle import Mode
from tests.firmware_py.test_ftp_server import Client, ack, nak, put
from tests.firmware_py.test_mav_engines import KEY, Link, of, texts
from tests.firmware_py.test_mav_engines import ack as cmd_ack

S = 1_000_000
GCS_HB = (m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)


def float_item(link, seq, x, y, z=0.0, frame=m.MAV_FRAME_LOCAL_NED, p1=0.0):
    return link.gcs.mission_item_encode(1, 1, seq, frame, m.MAV_CMD_NAV_WAYPOINT, 0, 1, p1, 0, 0, 0, x, y, z, 0)


def upload_one(link, item):
    assert of(link.send(link.gcs.mission_count_encode(1, 1, 1, 0)), "MISSION_REQUEST_INT")
    (a,) = of(link.send(item), "MISSION_ACK")
    return a.type


# --- per-message isolation --------------------------------------------------------------------

@pytest.mark.parametrize(("x", "y", "z", "p1", "code"), [
    (math.nan, 1.0, 0.0, 0.0, m.MAV_MISSION_INVALID_PARAM5_X),
    (math.inf, 1.0, 0.0, 0.0, m.MAV_MISSION_INVALID_PARAM5_X),
    (1.0, -math.inf, 0.0, 0.0, m.MAV_MISSION_INVALID_PARAM6_Y),
    (1.0, math.nan, 0.0, 0.0, m.MAV_MISSION_INVALID_PARAM6_Y),
    (1e9, 1.0, 0.0, 0.0, m.MAV_MISSION_INVALID_PARAM5_X),  # 1e13 after scaling: not an int32
    (1.0, 1.0, math.nan, 0.0, m.MAV_MISSION_INVALID_PARAM7),
    (1.0, 1.0, 0.0, math.inf, m.MAV_MISSION_INVALID_PARAM1),
])
def test_non_finite_or_out_of_range_mission_items_are_refused(x, y, z, p1, code):
    link = Link()
    assert upload_one(link, float_item(link, 0, 2.0, 1.0)) == m.MAV_MISSION_ACCEPTED
    assert upload_one(link, float_item(link, 0, x, y, z, p1=p1)) == code
    assert len(link.vehicle.mission) == 1 and len(link.node.mission.items) == 1  # the old mission is kept
    assert link.node.handler_errors == {}  # refused by validation, not by the catch-all


def test_out_of_range_global_items_and_goals_are_refused():
    link = Link()
    item = link.gcs.mission_item_int_encode(1, 1, 0, m.MAV_FRAME_GLOBAL_INT, m.MAV_CMD_NAV_WAYPOINT, 0, 1,
                                            0, 0, 0, 0, 950_000_000, 0, 0, 0)
    assert upload_one(link, item) == m.MAV_MISSION_INVALID_PARAM5_X
    link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    goal = link.gcs.set_position_target_global_int_encode(0, 1, 1, m.MAV_FRAME_GLOBAL_INT, 0,
                                                          0, 2_000_000_000, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    assert "goal refused: latitude/longitude out of range" in texts(link.send(goal))


def test_failsafe_trips_on_time_while_nan_items_keep_arriving():
    link = Link()
    link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)
    link.send(link.gcs.heartbeat_encode(*GCS_HB))
    t_last, period = link.now, robot_spec.CONTROL_PERIOD_US
    timeout = link.node.params.get("FS_GCS_TOUT_MS") * 1000
    while not link.node.failsafe:
        link.send(link.gcs.mission_count_encode(1, 1, 1, 0))
        link.send(float_item(link, 0, math.nan, math.inf))
        link.send(link.gcs.command_long_encode(1, 1, m.MAV_CMD_DO_SET_MODE, 0, math.nan, math.inf, 0, 0, 0, 0, 0))
        link.tick(period)
        assert link.now <= t_last + timeout + period
    assert link.vehicle.failsafe_calls == [True]


def test_an_exception_in_a_handler_is_counted_and_the_node_carries_on(monkeypatch):
    link = Link()

    def broken(*_a, **_k):
        raise RuntimeError("handler bug")

    monkeypatch.setattr(link.node.commands, "handle", broken)
    for _ in range(3):
        replies = link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert texts(replies) == ["COMMAND_LONG refused: RuntimeError"]
    assert link.node.handler_errors == {"COMMAND_LONG": 3}
    monkeypatch.setattr(link.node.telemetry, "due", broken)  # a broken telemetry part
    link.send(link.gcs.heartbeat_encode(*GCS_HB))
    link.tick(10 * S)  # ... does not stop the failsafe check
    assert link.node.failsafe and link.node.handler_errors["tick:_tick_telemetry"] == 1


# --- signing ------------------------------------------------------------------------------------

def forged(link, timestamp: int):
    """A correctly signed ARM stamped `timestamp` (a key holder with a broken clock)."""
    link.gcs.signing.timestamp = timestamp
    return link.frame(link.gcs.command_long_encode(1, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))


def test_signed_frame_near_2_48_is_dropped_and_a_correct_gcs_stays_reachable_after_restart(tmp_path):
    key_file = tmp_path / "key.txt"
    key_file.write_text("qnav test key\n")
    link = Link(tmp_path, key=KEY, boot_key_file=key_file)
    own = link.node.signing.timestamp
    assert link.feed(forged(link, MAX_TIMESTAMP - 5)) == []
    assert link.feed(forged(link, own + FUTURE_WINDOW + 100)) == []
    assert link.node.signing.dropped_future == 2 and not link.vehicle.st.armed
    assert link.node.signing.current_timestamp(link.now) < own + FUTURE_WINDOW
    # a key holder slightly ahead (inside the window) is accepted but does not move the robot's clock
    assert cmd_ack(link.feed(forged(link, own + FUTURE_WINDOW // 2))) == m.MAV_RESULT_ACCEPTED
    assert link.node.signing.current_timestamp(link.now) < own + 100
    link.node.signing.persist(link.now)
    stored = json.loads((tmp_path / "params" / "signing.json").read_text())
    assert stored["timestamp"] <= MAX_TIMESTAMP and all(ts <= MAX_TIMESTAMP for *_k, ts in stored["streams"])
    # restart: a correct GCS (a new stream, stamped with the wall clock) gets in
    again = Link(tmp_path, key=KEY, boot_key_file=key_file)
    again.gcs.signing.link_id = 2
    again.gcs.signing.timestamp = wall_timestamp() + 100
    assert cmd_ack(again.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)) == m.MAV_RESULT_ACCEPTED
    assert again.node.signing.timestamp < own + FUTURE_WINDOW


def test_a_state_file_beyond_48_bits_is_reset_at_boot(tmp_path):
    (tmp_path / "params").mkdir()
    (tmp_path / "params" / "signing.json").write_text(json.dumps(
        {"version": 1, "timestamp": MAX_TIMESTAMP + 7, "key": KEY.hex(), "streams": [[1, 255, 190, 2**48 + 3]]}))
    link = Link(tmp_path, key=KEY)
    assert link.node.signing.timestamp <= wall_timestamp() + 10 and link.node.signing.streams == {}
    assert any("beyond the bound" in t for t in texts(link.tick()))
    assert cmd_ack(link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)) == m.MAV_RESULT_ACCEPTED


def test_replay_after_a_crash_is_refused_although_nothing_was_saved(tmp_path):
    key_file = tmp_path / "key.txt"
    key_file.write_text("qnav test key\n")
    link = Link(tmp_path, key=KEY, boot_key_file=key_file)
    link.node.signing.persist(link.now)  # an old save; the frame below never reaches the file
    captured = forged(link, link.node.signing.timestamp + 10)
    assert cmd_ack(link.feed(captured)) == m.MAV_RESULT_ACCEPTED
    # kill -9: no persist; the next boot's replay floor refuses the captured frame
    again = Link(tmp_path, key=KEY, boot_key_file=key_file)
    assert again.feed(captured) == [] and again.node.signing.dropped_replay == 1
    assert not again.vehicle.st.armed


def test_unsigned_setup_signing_over_a_network_link_is_refused_unless_enabled_on_the_robot(tmp_path):
    link = Link(tmp_path)
    setup = link.gcs.setup_signing_encode(1, 1, list(b"k" * 32), link.node.signing.timestamp)
    assert texts(link.send(setup)) == ["unsigned SETUP_SIGNING refused: SIGN_NET_SETUP=0"]
    assert link.node.signing.key is None and link.node.refused_setup_signing == 1
    assert not (tmp_path / "params" / "signing.json").exists() or \
        json.loads((tmp_path / "params" / "signing.json").read_text())["key"] == ""
    # the parameter cannot be set over MAVLink ...
    (value,) = of(link.send(link.gcs.param_set_encode(1, 1, b"SIGN_NET_SETUP", 1, 6)), "PARAM_VALUE")
    assert value.param_value == 0 and link.node.params.get("SIGN_NET_SETUP") == 0
    # ... only on the robot (params.json), then a restart
    (tmp_path / "params").mkdir(exist_ok=True)
    (tmp_path / "params" / "params.json").write_text(json.dumps({"version": 1, "params": {"SIGN_NET_SETUP": 1}}))
    again = Link(tmp_path)
    assert texts(again.send(setup)) == ["signing key set"] and again.node.signing.key == b"k" * 32
    # an initial timestamp near 2^48 does not wedge the clock
    serial = Link()
    serial.node.network_link = False  # a serial link: physical access
    far = serial.gcs.setup_signing_encode(1, 1, list(KEY), MAX_TIMESTAMP - 1)
    assert "initial timestamp too far ahead" in texts(serial.send(far))[0]
    assert serial.node.signing.key == KEY and serial.node.signing.timestamp < MAX_TIMESTAMP // 2


def test_network_urls_are_told_from_serial_devices():
    for url in ("udpin:0.0.0.0:14550", "udpout:127.0.0.1:14550", "tcp:host:5760", "tcpin:0.0.0.0:5760",
                "127.0.0.1:14550"):
        assert is_network_url(url), url
    for url in ("/dev/ttyUSB0", "/dev/pts/3", "COM3"):
        assert not is_network_url(url), url


# --- GCS identity -----------------------------------------------------------------------------

def test_only_sysid_mygcs_keeps_the_failsafe_alive_a_router_heard_first_owns_nothing():
    """Issue 29 finding 2: with the old default (the first GCS heard owns the
    failsafe) a router's own GCS heartbeat (mavp2p: sysid 125) heard first
    kept the failsafe quiet after the operator went silent."""
    link = Link()
    assert link.node.params.get("SYSID_MYGCS") == 255  # ArduPilot's default
    router = m.MAVLink(None, 125, 190)
    router_hb = bytes(router.heartbeat_encode(*GCS_HB).pack(router))
    link.feed(router_hb)  # heard first: owns nothing
    link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    link.send(link.gcs.heartbeat_encode(*GCS_HB))  # the operator, sysid 255
    period = robot_spec.CONTROL_PERIOD_US
    t_last = link.now
    while not link.node.failsafe:
        link.feed(router_hb)  # the router beats every period: keeps nothing alive
        link.tick(period)
    assert link.now <= t_last + link.node.params.get("FS_GCS_TOUT_MS") * 1000 + period
    assert link.node.foreign_gcs_heartbeats > 0
    assert not texts(link.feed(router_hb)) and link.node.failsafe  # and clears nothing
    assert "GCS failsafe cleared" in texts(link.send(link.gcs.heartbeat_encode(*GCS_HB)))
    # the operator hands the robot to system 200
    spoof = m.MAVLink(None, 200, 190)
    hb = bytes(spoof.heartbeat_encode(*GCS_HB).pack(spoof))
    link.send(link.gcs.param_set_encode(1, 1, b"SYSID_MYGCS", 200, 6))
    while not link.node.failsafe:
        link.send(link.gcs.heartbeat_encode(*GCS_HB))  # 255 no longer counts
        link.tick(period)
    assert "GCS failsafe cleared" in texts(link.feed(hb))


def test_sysid_mygcs_zero_follows_the_first_gcs_heard():
    link = Link()
    link.send(link.gcs.param_set_encode(1, 1, b"SYSID_MYGCS", 0, 6))
    link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    other = m.MAVLink(None, 77, 190)
    link.feed(bytes(other.heartbeat_encode(*GCS_HB).pack(other)))
    assert link.node.gcs_sysid == 77
    period = robot_spec.CONTROL_PERIOD_US
    while not link.node.failsafe:
        link.send(link.gcs.heartbeat_encode(*GCS_HB))  # 255 came second: keeps nothing alive
        link.tick(period)
    assert link.node.foreign_gcs_heartbeats > 0


# --- FTP: sessions and quotas ---------------------------------------------------------------

@pytest.fixture
def server(tmp_path):
    return FtpServer(Storage(tmp_path / "root", quota_bytes=200_000, quota_files=12, quota_dirs=4))


def test_another_system_cannot_read_terminate_or_reset_a_session(server):
    owner, thief = Client(server, owner=(255, 190)), Client(server, owner=(66, 1))
    put(owner, "/policies/secret.qtab", b"top secret")
    assert ack(owner.one(Op.CREATE_FILE, b"/policies/upload.qtab"))
    assert ack(owner.one(Op.WRITE_FILE, b"half", offset=0))
    assert nak(thief.one(Op.WRITE_FILE, b"evil", offset=0), Nak.INVALID_SESSION)
    assert nak(thief.one(Op.TERMINATE_SESSION), Nak.INVALID_SESSION)  # would commit the half file
    assert not server.storage.exists("/policies/upload.qtab")
    assert ack(thief.one(Op.RESET_SESSIONS))  # resets its own (none)
    assert ack(owner.one(Op.WRITE_FILE, b"-done", offset=4))
    assert ack(owner.one(Op.TERMINATE_SESSION))
    assert server.storage.read_bytes("/policies/upload.qtab") == b"half-done"
    assert ack(owner.one(Op.OPEN_FILE_RO, b"/policies/secret.qtab"))
    assert nak(thief.one(Op.READ_FILE, size=100), Nak.INVALID_SESSION)
    assert server.stats.foreign_session_requests >= 3


def test_idle_sessions_cannot_lock_other_clients_out(server):
    squatters = [Client(server, owner=(100 + i, 1)) for i in range(2)]
    for c in squatters:
        for sid in range(2):
            assert ack(c.one(Op.CREATE_FILE, f"/policies/s{c.owner[0]}_{sid}".encode(), session=sid))
    late = Client(server, owner=(255, 190))
    assert nak(late.one(Op.CREATE_FILE, b"/policies/mine"), Nak.NO_SESSIONS_AVAILABLE)  # all busy just now
    late.now = 1_500_000  # the squatters have been idle > 1 s
    assert ack(late.one(Op.CREATE_FILE, b"/policies/mine"))
    assert server.stats.evicted_sessions == 1
    late.now = 7_000_000  # and idle sessions expire after 5 s
    server.expire(late.now + 1)
    assert server.sessions == {}


def test_sparse_write_and_huge_truncate_cannot_fill_the_quota(server):
    c = Client(server)
    assert ack(c.one(Op.CREATE_FILE, b"/policies/sparse"))
    r = c.one(Op.WRITE_FILE, b"x", offset=199_000)  # one byte at the end of the quota
    assert r[2] == Op.NAK and r[7][:2] == bytes([Nak.FAIL_ERRNO, 22])
    assert ack(c.one(Op.WRITE_FILE, b"y", offset=1000))  # a small hole (blocks in flight) is fine
    assert ack(c.one(Op.TERMINATE_SESSION))
    assert server.storage.usage() < 2000
    put(c, "/policies/small", b"abc")
    for length in (0xFFFFFFFF, 250_000):
        r = c.one(Op.TRUNCATE_FILE, b"/policies/small", offset=length)
        assert r[2] == Op.NAK and r[7][:2] == bytes([Nak.FAIL_ERRNO, 28])  # ENOSPC, nothing allocated
    assert ack(c.one(Op.TRUNCATE_FILE, b"/policies/small", offset=10))
    assert server.storage.read_bytes("/policies/small") == b"abc" + bytes(7)


def _create_until_enospc(c: Client, op: Op, path: str) -> int:
    """Create path.format(0), path.format(1), ... until the server NAKs (it must be ENOSPC); how many it made.
    A created file's session is terminated before the next."""
    made = 0
    while (r := c.one(op, path.format(made).encode()))[2] != Op.NAK:
        if op == Op.CREATE_FILE:
            assert ack(c.one(Op.TERMINATE_SESSION))
        made += 1
    assert r[7][:2] == bytes([Nak.FAIL_ERRNO, 28])
    return made


def test_file_and_directory_quotas(server):
    c = Client(server)
    made = _create_until_enospc(c, Op.CREATE_DIRECTORY, "/d{}")
    layout = len(LAYOUT_DIRS)
    assert made == 4 - layout  # the layout's directories count
    files = _create_until_enospc(c, Op.CREATE_FILE, "/f{}")
    assert files == 12
    assert len(os.listdir(server.storage.root)) == layout + made + files
