"""VehicleView fed with real pymavlink-encoded and -decoded frames."""

from __future__ import annotations

import math

import pytest

from firmware_py.mavlink.dialect import mavlink2 as mavlink
from firmware_py.vehicle import CtrlState, Mode
from ground_station.monitor.model import VehicleView
from tests.support.rover_script import encoder, frame, gcs_mission_items


def wire(mav: mavlink.MAVLink, *msgs) -> bytes:
    return b"".join(frame(mav, m) for m in msgs)


def decode(buf: bytes, key: bytes | None = None) -> list:
    rx = mavlink.MAVLink(None)
    rx.robust_parsing = True
    if key is not None:
        rx.signing.secret_key = key
    return [m for m in rx.parse_buffer(buf) or [] if m.get_type() != "BAD_DATA"]


def feed(view: VehicleView, buf: bytes, t: float = 0.0, key: bytes | None = None) -> list:
    msgs = decode(buf, key)
    for m in msgs:
        view.update(m, t)
    return msgs


def heartbeat(mode=Mode.HOLD, armed=False, status=mavlink.MAV_STATE_STANDBY, vtype=mavlink.MAV_TYPE_GROUND_ROVER):
    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
    return mavlink.MAVLink_heartbeat_message(vtype, mavlink.MAV_AUTOPILOT_GENERIC, base, int(mode), status, 3)


@pytest.fixture
def rover():
    return encoder(1, 1)


def test_locks_onto_the_rover_and_ignores_other_systems(rover):
    view = VehicleView()
    gcs, other = encoder(255, 190), encoder(2, 1)
    gcs_hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
    feed(view, wire(gcs, gcs_hb))
    assert view.sysid is None and view.link.last_heartbeat_t is None
    feed(view, wire(rover, heartbeat(Mode.AUTO, armed=True, status=mavlink.MAV_STATE_ACTIVE)), t=10.0)
    assert view.sysid == 1 and view.compid == 1
    assert view.mode_name == "Auto" and view.armed and not view.failsafe
    feed(view, wire(other, heartbeat(Mode.HOLD), mavlink.MAVLink_local_position_ned_message(0, 9, 9, 0, 0, 0, 0)))
    assert view.mode == Mode.AUTO and view.x is None
    assert view.heartbeat_age(12.5) == pytest.approx(2.5)
    feed(view, wire(rover, heartbeat(Mode.HOLD, armed=True, status=mavlink.MAV_STATE_CRITICAL)), t=13.0)
    assert view.failsafe and view.mode_name == "Hold"


def test_ned_position_and_yaw_become_world_frame(rover):
    view = VehicleView()
    feed(view, wire(rover, heartbeat(),
                    mavlink.MAVLink_local_position_ned_message(100, 3.0, 1.0, 0.0, 0.4, 0.0, 0.0),
                    mavlink.MAVLink_attitude_message(100, 0.0, 0.0, 0.0, 0, 0, 0)))
    assert (view.x, view.y) == (1.0, 3.0)  # x east = NED y, y north = NED x
    assert (view.vx, view.vy) == (0.0, pytest.approx(0.4))
    assert view.heading == pytest.approx(math.pi / 2)  # yaw 0 = north = CCW 90° from east
    feed(view, wire(rover, mavlink.MAVLink_attitude_message(200, 0, 0, math.pi / 2, 0, 0, 0)))
    assert view.heading == pytest.approx(0.0, abs=1e-6)  # yaw +90° (clockwise) = east
    feed(view, wire(rover, mavlink.MAVLink_attitude_message(300, 0, 0, -3 * math.pi / 4, 0, 0, 0)))
    assert math.degrees(view.heading) == pytest.approx(-135.0)  # south-west


def test_trail_skips_tiny_moves(rover):
    view = VehicleView()
    feed(view, wire(rover, heartbeat()))
    for i in range(10):  # 1.5 cm steps: only every other one is >= 2 cm from the last trail point
        feed(view, wire(rover, mavlink.MAVLink_local_position_ned_message(i, 0.0, i * 0.015, 0, 0, 0, 0)))
    assert [round(p[0], 3) for p in view.trail] == [0.0, 0.03, 0.06, 0.09, 0.12]


def test_packet_loss_from_sequence_gaps_including_wraparound(rover):
    view = VehicleView()
    frames = [frame(rover, heartbeat())] + [
        frame(rover, mavlink.MAVLink_named_value_int_message(i, b"STATE_IDX", i)) for i in range(299)]
    dropped = {5, 6, 7, 100, 254, 255, 256, 290}  # crosses the 255 -> 0 wrap
    feed(view, b"".join(f for i, f in enumerate(frames) if i not in dropped))
    assert view.link.lost == len(dropped)
    assert view.link.received == len(frames) - len(dropped)
    assert view.link.loss_pct == pytest.approx(100 * len(dropped) / len(frames))


def test_signing_seen_and_verified_with_the_key():
    key = bytes(range(32))
    signer = encoder(1, 1, key=key)
    buf = wire(signer, heartbeat(), mavlink.MAVLink_named_value_int_message(0, b"ACTION", 2))
    blind = VehicleView()
    feed(blind, buf)
    assert blind.link.signing and blind.link.signed_frames == 2 and blind.link.verified_frames == 0
    keyed = VehicleView()
    feed(keyed, buf, key=key)
    assert keyed.link.verified_frames == 2 and keyed.action == 2
    plain = VehicleView()
    feed(plain, wire(encoder(1, 1), heartbeat()))
    assert not plain.link.signing


def test_sys_status_counters_and_load(rover):
    view = VehicleView()
    feed(view, wire(rover, heartbeat(), mavlink.MAVLink_sys_status_message(
        1, 1, 1, 237, 12000, -1, -1, 125, 17, 1, 2, 3, 4)))
    assert view.load_pct == pytest.approx(23.7)
    assert view.link.drop_rate_comm_pct == pytest.approx(1.25)
    assert view.link.rx_dropped == 17
    assert (view.link.can_errors, view.link.tick_overruns, view.link.signing_dropped) == (1, 2, 3)


def test_obstacle_distance_sectors(rover):
    view = VehicleView()
    d = [65535] * 72
    d[:8] = [50, 60, 201, 80, 1, 100, 110, 120]  # 201 > max: no obstacle; 1 < min: no reading
    feed(view, wire(rover, heartbeat(), mavlink.MAVLink_obstacle_distance_message(
        0, 0, d, 0, 2, 200, 45.0, 0.0, mavlink.MAV_FRAME_BODY_FRD)))
    assert len(view.sectors) == 8
    by_deg = {round(math.degrees(a)): r for a, r in view.sectors}
    assert by_deg[0] == pytest.approx(0.5)
    assert by_deg[-45] == pytest.approx(0.6)  # FRD index 1 = 45° clockwise = right-front
    assert by_deg[-90] is None and by_deg[180] is None
    assert by_deg[45] == pytest.approx(1.2)
    assert view.sector_max_m == pytest.approx(2.0)


def test_named_values_param_and_statustext_chunks(rover):
    view = VehicleView()
    msgs = [heartbeat()]
    for name, value in (("CTRL_ST", int(CtrlState.DRIVING)), ("STATE_IDX", 117), ("ACTION", 3),
                        ("Q0", 10), ("Q1", 40), ("Q2", 40), ("Q3", -5)):
        msgs.append(mavlink.MAVLink_named_value_int_message(5, name.encode(), value))
    # the shipped cell policy's id: float32 on the wire turns POLICY_ID into 3050702336 (0xb5d60600);
    # the exact id comes from its halves (issue 30 finding 6)
    pid = 0xB5D6060C
    msgs.append(mavlink.MAVLink_param_value_message(b"POLICY_ID", float(pid), mavlink.MAV_PARAM_TYPE_INT32, 5, 1))
    msgs.append(mavlink.MAVLink_param_value_message(b"POLICY_ID_HI", pid >> 16, mavlink.MAV_PARAM_TYPE_INT32, 5, 2))
    msgs.append(mavlink.MAVLink_param_value_message(b"POLICY_ID_LO", pid & 0xFFFF, mavlink.MAV_PARAM_TYPE_INT32, 5, 3))
    long_text = "x" * 50 + "tail"
    msgs.append(mavlink.MAVLink_statustext_message(4, long_text[:50].encode(), 9, 0))
    msgs.append(mavlink.MAVLink_statustext_message(4, long_text[50:].encode(), 9, 1))
    msgs.append(mavlink.MAVLink_statustext_message(6, b"hello", 0, 0))
    feed(view, wire(rover, *msgs), t=3.0)
    assert view.ctrl_name == "DRIVING" and view.state_index == 117 and view.action == 3
    assert view.q_row == {0: 10, 1: 40, 2: 40, 3: -5}
    assert view.policy_id == pid and "policy=0xb5d6060c" in view.status_line(3.0)
    assert [(e.severity_name, e.text) for e in view.log] == [("WARN", long_text), ("INFO", "hello")]
    feed(view, wire(rover, mavlink.MAVLink_named_value_int_message(6, b"STATE_IDX", -1)))
    assert view.q_row == {} and "state=-" in view.status_line(3.0)  # no decision: no stale row


def test_mission_goal_sources(rover):
    view = VehicleView()
    gcs = encoder(255, 190)
    items = [(1.25, 3.75), (4.75, 4.75)]
    feed(view, wire(gcs, *gcs_mission_items(gcs, items)))
    assert view.mission.items == {0: pytest.approx(items[0]), 1: pytest.approx(items[1])}
    feed(view, wire(rover, heartbeat(Mode.AUTO, armed=True),
                    mavlink.MAVLink_local_position_ned_message(0, 1.75, 1.25, 0, 0, 0, 0),
                    mavlink.MAVLink_mission_current_message(1, 2, 0, 0)))
    assert view.goal == pytest.approx(items[1])
    assert view.distance_to_goal() == pytest.approx(math.hypot(3.5, 3.0))
    feed(view, wire(rover, mavlink.MAVLink_mission_item_reached_message(1)))
    assert view.mission.reached == [1]
    # Guided: the robot's POSITION_TARGET_LOCAL_NED wins over the mission item
    feed(view, wire(rover, heartbeat(Mode.GUIDED, armed=True), mavlink.MAVLink_position_target_local_ned_message(
        0, mavlink.MAV_FRAME_LOCAL_NED, 0xDF8, 2.0, 0.5, 0, 0, 0, 0, 0, 0, 0, 0, 0)))
    assert view.goal == pytest.approx((0.5, 2.0))


def test_goal_estimate_from_nav_controller_output(rover):
    view = VehicleView()
    feed(view, wire(rover, heartbeat(Mode.GUIDED),
                    mavlink.MAVLink_local_position_ned_message(0, 1.0, 1.0, 0, 0, 0, 0),
                    mavlink.MAVLink_nav_controller_output_message(0, 0, 0, 90, 3, 0, 0, 0)))
    assert view.goal is None
    assert view.distance_to_goal() == 3.0
    assert view.goal_estimate() == pytest.approx((4.0, 1.0))  # bearing 90° = east


def test_status_line_reports_what_the_view_holds(rover):
    view = VehicleView()
    feed(view, wire(rover, heartbeat(Mode.AUTO, armed=True),
                    mavlink.MAVLink_local_position_ned_message(0, 2.0, 1.5, 0, 0, 0, 0),
                    mavlink.MAVLink_named_value_int_message(0, b"STATE_IDX", 42)), t=100.0)
    line = view.status_line(101.5)
    for part in ("hb_age=1.5s", "mode=Auto", "armed=yes", "x=1.50 y=2.00", "state=42", "signed=no"):
        assert part in line


def test_reads_what_the_robot_telemetry_builds():
    """Contract with firmware_py.mavlink.telemetry: the robot's own builders -> wire -> view."""
    from firmware_py import robot_spec
    from firmware_py.mavlink.params import ParamStore
    from firmware_py.mavlink.telemetry import STREAMS, NodeStats, Telemetry
    from firmware_py.vehicle import VehicleStatus

    mav = encoder(1, 1)
    tel = Telemetry(mav, ParamStore(None))
    ranges = [300, 400, 500, 600, 700, 800, 900, 1000]
    status_codes = [robot_spec.RANGE_VALID] * 8
    status_codes[2] = robot_spec.RANGE_TOO_FAR
    status_codes[5] = robot_spec.RANGE_INVALID
    st = VehicleStatus(time_us=5_000_000, state=CtrlState.DRIVING, mode=Mode.GUIDED, armed=True,
                       x_mm=1250, y_mm=3750, heading_mrad=785, speed_mm_s=300, goal_mm=(4750, 4750),
                       distance_to_goal_mm=3640, bearing_to_goal_mrad=0, ranges_mm=ranges,
                       range_status=status_codes, state_index=57, action=1, q_row=(5, 9, -3, 0),
                       mission_seq=0, mission_count=0, tick_overruns=4, can_errors=2)
    view = VehicleView()
    msgs = []
    for msg_id in STREAMS:
        msgs += tel.build(msg_id, st.time_us, st, NodeStats(load_permille=123))
    feed(view, wire(mav, *msgs), t=5.0)
    assert view.mode_name == "Guided" and view.armed and view.ctrl_name == "DRIVING"
    assert (view.x, view.y) == (pytest.approx(1.25), pytest.approx(3.75))
    assert view.heading == pytest.approx(0.785, abs=1e-3)
    assert view.speed == pytest.approx(0.3, abs=1e-3)
    assert view.goal == pytest.approx((4.75, 4.75))
    assert (view.state_index, view.action, view.q_row) == (57, 1, {0: 5, 1: 9, 2: -3, 3: 0})
    assert view.load_pct == pytest.approx(12.3)
    assert view.link.tick_overruns == 4 and view.link.can_errors == 2
    sectors = {round(math.degrees(a)): r for a, r in view.sectors}
    want = {round(a * 180 / 1000 / math.pi): r / 1000 for a, r in zip(robot_spec.SENSOR_ANGLES_MRAD, ranges, strict=True)}
    assert set(sectors) == set(want) - {round(robot_spec.SENSOR_ANGLES_MRAD[5] * 0.18 / math.pi)}
    for deg, rng in sectors.items():
        if deg == round(robot_spec.SENSOR_ANGLES_MRAD[2] * 0.18 / math.pi):
            assert rng is None  # too far: clear
        else:
            assert rng == pytest.approx(want[deg])


def test_a_chunked_text_whose_last_chunk_is_lost_is_logged_once_chunks_stop(rover):
    """statustext.py's promise, at the view: the terminator of a 60-char text is
    lost; the text is logged (as far as it goes) once other frames show that its
    chunks stopped, and flush_texts() logs one still pending at the end."""
    view = VehicleView()
    first = "motor driver fault: overcurrent on the left whe"[:50].ljust(50, ".")
    feed(view, wire(rover, heartbeat(), mavlink.MAVLink_statustext_message(3, first.encode(), 7, 0)), t=1.0)
    feed(view, wire(rover, heartbeat()), t=1.1)  # within STALE_S: the rest may still come
    assert [e.text for e in view.log] == []
    feed(view, wire(rover, heartbeat()), t=2.0)
    assert [(e.severity_name, e.text) for e in view.log] == [("ERROR", first)]
    second = "y" * 50
    feed(view, wire(rover, mavlink.MAVLink_statustext_message(4, second.encode(), 8, 0)), t=2.1)
    assert len(view.log) == 1
    view.flush_texts()
    assert [e.text for e in view.log] == [first, second] and view.log_total == 2


def test_the_q_row_is_taken_whole_never_half_updated(rover):
    """Issue 46: /vehicle was published after every NAMED_VALUE_INT, so a row showed Q0 of the new
    state beside Q1..Q3 of the old one. The robot sends Q_N before the row; the row changes whole."""
    from ground_station.logs.topics import RunTopics

    topics = RunTopics()
    for msg in decode(wire(rover, heartbeat())):
        topics.mavlink(msg, 0.5)
    rows = []
    for state, values in ((7, (1, 2, 3, 4)), (8, (50, 60, 70, 80))):
        group = [("STATE_IDX", state), ("ACTION", 0), ("CTRL_ST", int(CtrlState.DRIVING)), ("Q_N", len(values))]
        group += [(f"Q{i}", v) for i, v in enumerate(values)]
        for name, value in group:
            (msg,) = decode(wire(rover, mavlink.MAVLink_named_value_int_message(state, name.encode(), value)))
            rows += [r.message["q_row"] for r in topics.mavlink(msg, 1.0) if r.topic == "/vehicle"]
            assert topics.view.q_row in ({}, {0: 1, 1: 2, 2: 3, 3: 4}, {0: 50, 1: 60, 2: 70, 3: 80})
    assert rows == [[1, 2, 3, 4], [50, 60, 70, 80]]
