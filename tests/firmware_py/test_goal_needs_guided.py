"""Goals from the link are taken in Guided only (issue 43, finding 2), as
ArduPilot Rover takes them: SET_POSITION_TARGET_LOCAL_NED /
SET_POSITION_TARGET_GLOBAL_INT and a guided-mode waypoint (current=2) sent
while the robot is in Hold (or Auto, Manual) are refused with one STATUSTEXT
and never switch the mode; DO_REPOSITION switches to Guided only with its
CHANGE_MODE flag. The real Controller behind the real MavNode."""

from __future__ import annotations

import pytest

from firmware_py import robot_spec
from firmware_py.control.controller import Controller
from firmware_py.mavlink import frames as mav_frames
from firmware_py.mavlink.dialect import mavlink2 as m
from firmware_py.mavlink.node import MavNode
from firmware_py.mavlink.params import ParamStore
from firmware_py.mavlink.signing import Signing
from firmware_py.vehicle import CtrlState, Mode, VehicleConfig
from tests.support.controller_rig import Kinematic, Rig, cell_bfs_policy

GCS = (255, 190)
GOAL_MM = robot_spec.cell_center_mm(3, 0, 4)  # a free cell of the map below


class RealLink:
    """A GCS codec and a MavNode over a real, armed Controller."""

    def __init__(self) -> None:
        pol = cell_bfs_policy(["....", "....", "....", "...."], [(3, 0), (0, 0)])
        start = robot_spec.cell_center_mm(0, 3, 4)
        self.ctrl = Controller(VehicleConfig(), pol, start_pose_mm=(*start, 0))
        self.rig = Rig(self.ctrl, Kinematic(start[0], start[1], 0.0))
        self.rig.tick()
        assert self.ctrl.arm() == (True, "")
        self.node = MavNode(self.ctrl, ParamStore(None), Signing(None))
        self.now = 1_000_000
        self.node.boot(self.now)
        self.gcs = m.MAVLink(None, *GCS)
        self._robot = m.MAVLink(None, 1, 1)

    def send(self, msg) -> list:
        parsed = m.MAVLink(None).parse_char(bytes(msg.pack(self.gcs)))
        return [m.MAVLink(None).parse_char(bytes(r.pack(self._robot))) for r in self.node.handle(parsed, self.now)]

    def set_mode(self, mode: Mode) -> None:
        self.send(self.gcs.command_long_encode(1, 1, m.MAV_CMD_DO_SET_MODE, 0,
                                               m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(mode), 0, 0, 0, 0, 0))
        assert self.ctrl.mode == mode

    def local_goal(self) -> list:
        n, e = GOAL_MM[1] / 1000, GOAL_MM[0] / 1000  # NED: north, east
        return self.send(self.gcs.set_position_target_local_ned_encode(
            0, 1, 1, m.MAV_FRAME_LOCAL_NED, 0xFFF8, n, e, 0, 0, 0, 0, 0, 0, 0, 0, 0))

    def global_goal(self) -> list:
        lat, lon = mav_frames.world_to_global(*GOAL_MM, self.node.params.get("ORIGIN_LAT"),
                                              self.node.params.get("ORIGIN_LON"))
        return self.send(self.gcs.set_position_target_global_int_encode(
            0, 1, 1, m.MAV_FRAME_GLOBAL_INT, 0xFFF8, lat, lon, 0, 0, 0, 0, 0, 0, 0, 0, 0))

    def guided_waypoint(self) -> list:
        lat, lon = mav_frames.world_to_global(*GOAL_MM, self.node.params.get("ORIGIN_LAT"),
                                              self.node.params.get("ORIGIN_LON"))
        return self.send(self.gcs.mission_item_int_encode(1, 1, 0, m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                          m.MAV_CMD_NAV_WAYPOINT, 2, 1, 0, 0, 0, 0, lat, lon, 0))

    def reposition(self, flags: int) -> list:
        lat, lon = mav_frames.world_to_global(*GOAL_MM, self.node.params.get("ORIGIN_LAT"),
                                              self.node.params.get("ORIGIN_LON"))
        return self.send(self.gcs.command_int_encode(1, 1, m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                                     m.MAV_CMD_DO_REPOSITION, 0, 0, -1, flags, 0, 0, lat, lon, 0.0))


def texts(replies) -> list[str]:
    return [r.text for r in replies if r.get_type() == "STATUSTEXT"]


def of(replies, kind: str) -> list:
    return [r for r in replies if r.get_type() == kind]


@pytest.mark.parametrize("way", ["local", "global", "waypoint"])
@pytest.mark.parametrize("mode", [Mode.HOLD, Mode.AUTO, Mode.MANUAL])
def test_a_goal_outside_guided_is_refused_and_the_mode_is_kept(way, mode):
    link = RealLink()
    if mode != Mode.HOLD:
        if mode == Mode.AUTO:  # Auto needs a mission: it starts driving it, and the goal must not replace it
            assert link.ctrl.set_mission([robot_spec.cell_center_mm(0, 0, 4)])[0]
        link.set_mode(mode)
    before = link.ctrl.state
    replies = {"local": link.local_goal, "global": link.global_goal, "waypoint": link.guided_waypoint}[way]()
    assert link.ctrl.mode == mode, link.ctrl.mode
    assert link.ctrl.state == before
    assert not of(replies, "POSITION_TARGET_LOCAL_NED")
    (text,) = texts(replies)
    assert text.endswith(f"mode {mode.name.title()}, not Guided"), text
    assert text.startswith("guided goal refused:" if way == "waypoint" else "goal refused:"), text


@pytest.mark.parametrize("way", ["local", "global", "waypoint"])
def test_in_guided_the_same_goal_is_taken(way):
    link = RealLink()
    link.set_mode(Mode.GUIDED)
    replies = {"local": link.local_goal, "global": link.global_goal, "waypoint": link.guided_waypoint}[way]()
    assert not [t for t in texts(replies) if "refused" in t], texts(replies)
    assert link.ctrl.state == CtrlState.DRIVING and link.ctrl.mode == Mode.GUIDED


def test_do_reposition_switches_to_guided_only_with_its_change_mode_flag():
    link = RealLink()
    replies = link.reposition(0)  # no CHANGE_MODE: ArduPilot Rover denies it outside Guided
    assert of(replies, "COMMAND_ACK")[0].result == m.MAV_RESULT_DENIED
    assert any("reposition refused: mode Hold" in t for t in texts(replies)), texts(replies)
    assert link.ctrl.mode == Mode.HOLD and link.ctrl.state == CtrlState.HOLD
    replies = link.reposition(m.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE)
    assert of(replies, "COMMAND_ACK")[0].result == m.MAV_RESULT_ACCEPTED
    assert link.ctrl.mode == Mode.GUIDED and link.ctrl.state == CtrlState.DRIVING


def test_go_to_is_mode_guided_and_the_goal_and_keeps_the_other_refusals_first():
    ctrl = Controller(VehicleConfig(), cell_bfs_policy(["...."], [(3, 0)]))
    assert ctrl.set_goal(1750, 250) == (False, "disarmed: arm first")
    assert ctrl.go_to(1750, 250) == (False, "disarmed: arm first")
    assert ctrl.mode == Mode.HOLD
