"""Guided go-to and the robot's map, driven through the MAVLink engines with
real frames (tests/firmware_py/test_mav_engines.Link): DO_REPOSITION as
COMMAND_INT and COMMAND_LONG, the "guided mode" waypoint (current=2), the
position-target messages, mission items and goals checked against the map,
SYS_STATUS without a fence; and the controller's policy telemetry holding
the decision in force."""

from __future__ import annotations

import pytest

from firmware_py import robot_spec
from firmware_py.control.controller import Controller
from firmware_py.mavlink import frames as mav_frames
from firmware_py.mavlink.dialect import mavlink2 as m
from firmware_py.vehicle import CtrlState, Mode, VehicleConfig
from tests.firmware_py.test_mav_engines import Link, ack, of, texts, upload
from tests.support.controller_rig import Kinematic, Rig, cell_bfs_policy, sector_seek_policy

MAP_MM = (5000, 4000)  # 5 m east x 4 m north


def armed_link(map_mm=MAP_MM) -> Link:
    link = Link()
    link.vehicle.st.map_mm = map_mm
    link.cmd(m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert link.vehicle.st.armed
    return link


def text_of(replies) -> str:
    """The STATUSTEXTs of one reply, chunks joined (long reasons span several)."""
    return "".join(texts(replies))


def origin(link):
    return link.node.params.get("ORIGIN_LAT"), link.node.params.get("ORIGIN_LON")


def reposition_int(link, frame, x, y, flags=m.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE):
    return link.send(link.gcs.command_int_encode(1, 1, frame, m.MAV_CMD_DO_REPOSITION, 0, 0,
                                                 -1, flags, 0, 0, x, y, 0.0))


def test_do_reposition_command_int_global_as_mavproxy_sends_it_becomes_a_guided_goal():
    link = armed_link()
    lat, lon = mav_frames.world_to_global(3000, 1500, *origin(link))
    replies = reposition_int(link, m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, lat, lon)
    assert ack(replies) == m.MAV_RESULT_ACCEPTED
    assert link.vehicle.st.mode == Mode.GUIDED  # the CHANGE_MODE flag switched it
    assert link.vehicle.st.goal_mm == pytest.approx((3000, 1500), abs=12)  # 1e-7 deg ~ 11 mm
    (echo,) = of(replies, "POSITION_TARGET_LOCAL_NED")
    assert (echo.x, echo.y) == pytest.approx((1.5, 3.0), abs=0.012)  # north, east


def test_do_reposition_command_long_degrees_and_local_frame_command_int():
    link = armed_link()
    lat, lon = mav_frames.world_to_global(1000, 2000, *origin(link))
    assert ack(link.cmd(m.MAV_CMD_DO_REPOSITION, -1, m.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, 0,
                        lat / 1e7, lon / 1e7, 0)) == m.MAV_RESULT_ACCEPTED
    # float32 degrees: ~0.42 m steps in latitude near 47 deg (why COMMAND_INT exists)
    assert link.vehicle.st.goal_mm == pytest.approx((1000, 2000), abs=250)
    # LOCAL_NED: metres * 1e4, x north
    assert ack(reposition_int(link, m.MAV_FRAME_LOCAL_NED, 30_000, 45_000)) == m.MAV_RESULT_ACCEPTED
    assert link.vehicle.st.goal_mm == (4500, 3000)


def test_do_reposition_refusals_say_why_and_keep_the_goal():
    link = armed_link()
    lat0, lon0 = origin(link)
    assert ack(reposition_int(link, m.MAV_FRAME_LOCAL_NED, 10_000, 10_000)) == m.MAV_RESULT_ACCEPTED
    before = link.vehicle.st.goal_mm
    far_lat, far_lon = mav_frames.world_to_global(1250_000, 1000, lat0, lon0)  # 1.25 km east
    replies = reposition_int(link, m.MAV_FRAME_GLOBAL_INT, far_lat, far_lon)
    assert ack(replies) == m.MAV_RESULT_DENIED
    text = text_of(replies)
    assert text.startswith("reposition refused:") and "east/west of the map's 0..5 x 0..4 m" in text
    replies = reposition_int(link, m.MAV_FRAME_GLOBAL_INT, 0x7FFFFFFF, 0x7FFFFFFF)
    assert ack(replies) == m.MAV_RESULT_DENIED and text_of(replies) == "reposition refused: no position given"
    replies = reposition_int(link, m.MAV_FRAME_BODY_FRD, 1, 1)
    assert ack(replies) == m.MAV_RESULT_DENIED and "frame 12 unsupported" in text_of(replies)
    assert ack(link.cmd(m.MAV_CMD_DO_REPOSITION, -1, 1, 0, 0, float("nan"), float("nan"), 0)) == m.MAV_RESULT_DENIED
    assert link.vehicle.st.goal_mm == before
    # without the CHANGE_MODE flag in Hold: the vehicle's own refusal comes back
    link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.HOLD)
    replies = reposition_int(link, m.MAV_FRAME_LOCAL_NED, 20_000, 20_000, flags=0)
    assert ack(replies) == m.MAV_RESULT_DENIED and text_of(replies) == "reposition refused: not in Guided"


def test_guided_mode_waypoint_current_2_is_a_goal_acknowledged_by_mission_ack():
    link = armed_link()
    lat, lon = mav_frames.world_to_global(2000, 3000, *origin(link))
    link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)
    replies = link.send(link.gcs.mission_item_int_encode(1, 1, 0, m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                          m.MAV_CMD_NAV_WAYPOINT, 2, 0, 0, 0, 0, 0, lat, lon, 0, 0))
    (a,) = of(replies, "MISSION_ACK")
    assert a.type == m.MAV_MISSION_ACCEPTED and link.vehicle.st.goal_mm == pytest.approx((2000, 3000), abs=12)
    lat, lon = mav_frames.world_to_global(2000, 9000, *origin(link))  # 9 m north of a 4 m map
    replies = link.send(link.gcs.mission_item_int_encode(1, 1, 0, m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                          m.MAV_CMD_NAV_WAYPOINT, 2, 0, 0, 0, 0, 0, lat, lon, 0, 0))
    (a,) = of(replies, "MISSION_ACK")
    assert a.type == m.MAV_MISSION_INVALID_PARAM5_X and "north/south" in text_of(replies)


def test_mission_items_off_the_map_are_refused_with_the_field_and_the_old_mission_kept():
    link = armed_link()
    a, _ = upload(link, [(m.MAV_FRAME_LOCAL_NED, 10_000, 10_000)])
    assert a.type == m.MAV_MISSION_ACCEPTED and link.vehicle.mission == [(1000, 1000)]
    # 1.25 km north in the local frame (x is north): param5 / x
    a, replies = upload(link, [(m.MAV_FRAME_LOCAL_NED, 10_000, 10_000), (m.MAV_FRAME_LOCAL_NED, 12_500_000, 0)])
    assert a.type == m.MAV_MISSION_INVALID_PARAM5_X
    assert "mission item 1 refused: (0.00, 1250.00) m is north/south" in text_of(replies)
    # west of the map in the global frame: param6 / y
    lat, lon = mav_frames.world_to_global(-700, 1000, *origin(link))
    a, replies = upload(link, [(m.MAV_FRAME_GLOBAL_INT, lat, lon)])
    assert a.type == m.MAV_MISSION_INVALID_PARAM6_Y and "east/west" in text_of(replies)
    assert link.vehicle.mission == [(1000, 1000)]
    # no map known (no policy): nothing to check against
    link.vehicle.st.map_mm = None
    a, _ = upload(link, [(m.MAV_FRAME_LOCAL_NED, 12_500_000, 0)])
    assert a.type == m.MAV_MISSION_ACCEPTED


def test_position_target_global_off_the_map_refused():
    link = armed_link()
    link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)
    lat, lon = mav_frames.world_to_global(6000, 1000, *origin(link))
    msg = link.gcs.set_position_target_global_int_encode(0, 1, 1, m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0xFFF8,
                                                         lat, lon, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    replies = link.send(msg)
    assert text_of(replies).startswith("goal refused: (6.00, 1.00) m is east/west")
    lat, lon = mav_frames.world_to_global(4000, 1000, *origin(link))
    msg = link.gcs.set_position_target_global_int_encode(0, 1, 1, m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0xFFF8,
                                                         lat, lon, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    assert of(link.send(msg), "POSITION_TARGET_LOCAL_NED")
    assert link.vehicle.st.goal_mm == pytest.approx((4000, 1000), abs=12)


def test_sys_status_claims_no_fence_and_reports_it_healthy():
    link = Link()
    link.tick()
    (st,) = of(link.node.telemetry.build(m.MAVLINK_MSG_ID_SYS_STATUS, link.now, link.vehicle.status(),
                                         link.node.stats), "SYS_STATUS")
    assert not st.onboard_control_sensors_present & m.MAV_SYS_STATUS_GEOFENCE
    assert not st.onboard_control_sensors_enabled & m.MAV_SYS_STATUS_GEOFENCE
    assert st.onboard_control_sensors_health & m.MAV_SYS_STATUS_GEOFENCE  # a clear bit reads "breach"


# --- the controller: map extent and the decision in force -----------------------------------------

def test_controller_reports_the_policy_map_extent():
    pol = cell_bfs_policy(["....", "....", "...."], [(3, 0)])
    ctrl = Controller(VehicleConfig(), pol)
    assert ctrl.status().map_mm == (4 * 500, 3 * 500)
    assert Controller(VehicleConfig(), None).status().map_mm is None


@pytest.mark.parametrize("kind", ["cell", "sector"])
def test_policy_telemetry_holds_the_decision_in_force_while_driving(kind):
    if kind == "cell":
        pol = cell_bfs_policy(["....", ".@@.", "....", "...."], [(0, 3)])
        goal = robot_spec.cell_center_mm(0, 3, 4)
    else:
        pol = sector_seek_policy()
        goal = (1750, 1750)
    start = robot_spec.cell_center_mm(0, 0, 4)
    ctrl = Controller(VehicleConfig(), pol, start_pose_mm=(*start, 0))
    rig = Rig(ctrl, Kinematic(start[0], start[1], 0.0))
    rig.tick()
    assert ctrl.arm() == (True, "")
    assert ctrl.status().action == -1  # armed, no goal: nothing in force
    assert ctrl.go_to(*goal) == (True, "")
    samples = []

    def sample():
        st = ctrl.status()
        if st.state == CtrlState.DRIVING:
            samples.append((st.state_index, st.action, len(st.q_row)))
        return st.state == CtrlState.HOLD

    rig.run_until(sample, 1500)
    assert len(samples) > 20
    assert all(s >= 0 and a >= 0 and n > 0 for s, a, n in samples), samples[:5]
    if kind == "cell":  # one decision per cell move, held in between
        assert len({s for s, _, _ in samples}) < len(samples) / 5
    assert ctrl.status().action == -1 and ctrl.status().q_row == ()  # HOLD again: none in force


def test_statustext_of_whole_chunks_ends_with_an_empty_chunk():
    """MAVProxy (and the spec) read a full 50-byte last chunk as "more to come"."""
    link = Link()
    texts_100 = link.node.telemetry.statustext("x" * 100)
    assert [len(t.text) for t in texts_100] == [50, 50, 0]
    assert [t.chunk_seq for t in texts_100] == [0, 1, 2] and len({t.id for t in texts_100}) == 1
    assert [len(t.text) for t in link.node.telemetry.statustext("y" * 70)] == [50, 20]
    assert [t.id for t in link.node.telemetry.statustext("z" * 50)] == [0]  # one frame: no chunking


def local_target(link, frame, x, y, mask=0xFFF8):
    return link.send(link.gcs.set_position_target_local_ned_encode(0, 1, 1, frame, mask, x, y, 0,
                                                                   0, 0, 0, 0, 0, 0, 0, 0))


@pytest.mark.parametrize("frame, x, y, heading_mrad, want_mm", [
    # LOCAL_OFFSET_NED: x north, y east of the robot (heading does not matter)
    (m.MAV_FRAME_LOCAL_OFFSET_NED, 1.0, 0.5, 1234, (2500, 2000)),
    # BODY_OFFSET_NED / BODY_NED: x forward, y right; robot at (2000, 1000) facing north (1571 mrad)
    (m.MAV_FRAME_BODY_OFFSET_NED, 1.0, 0.0, 1571, (2000, 2000)),
    (m.MAV_FRAME_BODY_OFFSET_NED, 0.0, 1.0, 1571, (3000, 1000)),  # right of north is east
    (m.MAV_FRAME_BODY_NED, 1.0, -0.5, 0, (3000, 1500)),  # facing east: left is north
    (m.MAV_FRAME_BODY_OFFSET_NED, -1.0, 0.0, 3142, (3000, 1000)),  # facing west, 1 m back
])
def test_position_target_offsets_from_the_robot_as_ardupilot_rover_reads_them(frame, x, y, heading_mrad, want_mm):
    link = armed_link()
    link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)
    link.vehicle.st.x_mm, link.vehicle.st.y_mm, link.vehicle.st.heading_mrad = 2000, 1000, heading_mrad
    replies = local_target(link, frame, x, y)
    (echo,) = of(replies, "POSITION_TARGET_LOCAL_NED")
    assert link.vehicle.st.goal_mm == pytest.approx(want_mm, abs=2)
    assert (echo.x, echo.y) == pytest.approx((want_mm[1] / 1000, want_mm[0] / 1000), abs=0.002)  # absolute NED


def test_position_target_offsets_are_checked_like_absolute_targets():
    link = armed_link()
    link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)
    link.vehicle.st.x_mm, link.vehicle.st.y_mm, link.vehicle.st.heading_mrad = 4500, 1000, 0
    old = link.vehicle.st.goal_mm
    # 1 m forward from 0.5 m before the east wall: off the map, refused with the reason, goal kept
    assert text_of(local_target(link, m.MAV_FRAME_BODY_OFFSET_NED, 1.0, 0.0)).startswith(
        "goal refused: (5.50, 1.00) m is east/west")
    assert text_of(local_target(link, m.MAV_FRAME_LOCAL_OFFSET_NED, float("nan"), 0.0)) == \
        "goal refused: position is not a finite number"
    assert "unsupported" in text_of(local_target(link, m.MAV_FRAME_BODY_FRD, 1.0, 0.0))
    assert link.vehicle.st.goal_mm == old


def test_mavproxy_position_command_body_ned_moves_the_goal_relative_to_the_robot():
    """MAVProxy's `position X Y Z` (cmdlong module) sends SET_POSITION_TARGET_LOCAL_NED
    in MAV_FRAME_BODY_NED with type_mask 3576 (position only): X forward, Y right."""
    link = armed_link()
    link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)
    link.vehicle.st.x_mm, link.vehicle.st.y_mm, link.vehicle.st.heading_mrad = 2750, 2750, 0  # facing east
    of(local_target(link, m.MAV_FRAME_BODY_NED, -1.5, -1.0, mask=3576), "POSITION_TARGET_LOCAL_NED")
    assert link.vehicle.st.goal_mm == pytest.approx((1250, 3750), abs=2)  # 1.5 m back, 1 m to the left


def guided_item(link, x, y):
    """A float MISSION_ITEM in LOCAL_NED with current=2 (the guided go-to)."""
    return link.send(link.gcs.mission_item_encode(1, 1, 0, m.MAV_FRAME_LOCAL_NED, m.MAV_CMD_NAV_WAYPOINT,
                                                  2, 0, 0, 0, 0, 0, x, y, 0, 0))


@pytest.mark.parametrize("x, y, code", [
    (float("nan"), 1.0, m.MAV_MISSION_INVALID_PARAM5_X),
    (float("inf"), 1.0, m.MAV_MISSION_INVALID_PARAM5_X),
    (3e38, 1.0, m.MAV_MISSION_INVALID_PARAM5_X),  # near float32 max (1e300 cannot be packed)
    (1.0, 3e5, m.MAV_MISSION_INVALID_PARAM6_Y),  # beyond the local frame's 200 km
])
def test_guided_waypoint_with_a_bad_position_is_refused_with_its_code_not_by_the_catch_all(x, y, code):
    link = armed_link(map_mm=None)  # no map: only the frame's range stands between the item and the goal
    link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)
    old = link.vehicle.st.goal_mm
    replies = guided_item(link, x, y)
    (a,) = of(replies, "MISSION_ACK")
    assert a.type == code
    assert text_of(replies).startswith("guided goal refused: mission item 0:")
    assert link.node.handler_errors == {} and link.vehicle.st.goal_mm == old


def test_do_reposition_and_position_targets_out_of_the_frame_range_are_refused():
    link = armed_link(map_mm=None)  # no map: the frame's range is the only check
    link.cmd(m.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED)
    old = link.vehicle.st.goal_mm
    replies = link.cmd(m.MAV_CMD_DO_REPOSITION, -1, 1, 0, 0, 1e9, 10.0, 0)  # COMMAND_LONG: degrees
    assert ack(replies) == m.MAV_RESULT_DENIED and "x=1e+09 out of range" in text_of(replies)
    replies = reposition_int(link, m.MAV_FRAME_GLOBAL_INT, 470_000_000, 2_000_000_000)  # lon 200 deg
    assert ack(replies) == m.MAV_RESULT_DENIED and text_of(replies).startswith("reposition refused: y=200")
    replies = reposition_int(link, m.MAV_FRAME_LOCAL_NED, 2_100_000_000, 0)  # 210 km north
    assert ack(replies) == m.MAV_RESULT_DENIED and "x=210000 out of range" in text_of(replies)
    assert text_of(local_target(link, m.MAV_FRAME_LOCAL_NED, 3e5, 0.0)).startswith("goal refused: x=300000 out")
    assert link.vehicle.st.goal_mm == old and link.node.handler_errors == {}
    # the limits themselves are positions
    assert ack(reposition_int(link, m.MAV_FRAME_LOCAL_NED, 20_000, 2_000_000_000)) == m.MAV_RESULT_ACCEPTED
