"""MAVLink commands (COMMAND_LONG / COMMAND_INT, SET_MODE) -> COMMAND_ACK.

Owns which MAV_CMDs the robot supports and the MAV_RESULT each outcome maps to: ACCEPTED; DENIED
when the vehicle (or a bad argument) refuses, with the reason as a STATUSTEXT sent just before the
ACK; TEMPORARILY_REJECTED when the same command would succeed later (reboot while armed, mission
upload in progress); UNSUPPORTED for anything else. DO_REPOSITION (the guided go-to) sets a goal on
the robot's map. A pure engine: `handle(msg, now_us, stats)` returns the replies.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from firmware_py.mavlink import frames as mav_frames
from firmware_py.mavlink.dialect import mavlink2
from firmware_py.mavlink.mission import (
    GLOBAL_FRAMES,
    LOCAL_FRAMES,
    MissionEngine,
    check_position,
    map_bounds_error,
)
from firmware_py.mavlink.telemetry import (
    MSG_ID_PROTOCOL_VERSION,
    STANDARD_MODES,
    STREAMS,
    NodeStats,
    Telemetry,
)
from firmware_py.vehicle import Mode, VehicleControl

M = mavlink2
SETTABLE_MODES = {Mode.MANUAL: "Manual", Mode.HOLD: "Hold", Mode.GUIDED: "Guided", Mode.AUTO: "Auto"}
INT32_MAX = 0x7FFFFFFF

ACCEPTED = M.MAV_RESULT_ACCEPTED
DENIED = M.MAV_RESULT_DENIED
TEMP_REJECTED = M.MAV_RESULT_TEMPORARILY_REJECTED
UNSUPPORTED = M.MAV_RESULT_UNSUPPORTED
# qnav's own command (MAVLink reserves MAV_CMD_USER_1..5 for the vehicle's use): forget the pose and
# localise globally on the policy's map; param1 1 = explore (armed in HOLD), 0 = stay put
CMD_LOCALISE_GLOBAL = M.MAV_CMD_USER_1
Reply = tuple[int, str, list[mavlink2.MAVLink_message]]  # (MAV_RESULT, STATUSTEXT reason, after the ACK)


def _verdict(outcome: tuple[bool, str], refused: str) -> Reply:
    """ACCEPTED, or DENIED with "<refused>: <the vehicle's reason>"."""
    ok, reason = outcome
    return (ACCEPTED, "", []) if ok else (DENIED, f"{refused}: {reason}", [])


class CommandHandler:
    """Executes commands on the vehicle / node and acknowledges them."""

    def __init__(self, mav: mavlink2.MAVLink, vehicle: VehicleControl, telemetry: Telemetry,
                 mission: MissionEngine, reboot: Callable[[], list[mavlink2.MAVLink_message]]) -> None:
        self.mav = mav
        self.vehicle = vehicle
        self.telemetry = telemetry
        self.mission = mission
        self._reboot = reboot  # performs the reboot; returns messages to send after the ACK

    def handle(self, msg: mavlink2.MAVLink_message, now_us: int, stats: NodeStats) -> list[mavlink2.MAVLink_message]:
        kind = msg.get_type()
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "SET_MODE":  # legacy message; ArduPilot answers it with a DO_SET_MODE ack
            result, reason, after = self._set_mode(msg.base_mode, msg.custom_mode)
            return self._reply(M.MAV_CMD_DO_SET_MODE, src, result, reason, after)
        if kind == "COMMAND_LONG":
            p = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        else:  # COMMAND_INT: x/y are ints, z float
            p = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z)
        try:
            if msg.command == M.MAV_CMD_DO_REPOSITION:
                result, reason, after = self._reposition(msg, now_us)
            else:
                result, reason, after = self._execute(msg.command, p, now_us, stats)
        except (OverflowError, ValueError):  # int() of a NaN/inf parameter: refuse, do not crash
            result, reason, after = DENIED, f"command {msg.command}: a parameter is not a finite number", []
        return self._reply(msg.command, src, result, reason, after)

    def _reply(self, command: int, src: tuple[int, int], result: int, reason: str,
               after: list[mavlink2.MAVLink_message]) -> list[mavlink2.MAVLink_message]:
        out: list[mavlink2.MAVLink_message] = []
        if reason:
            severity = M.MAV_SEVERITY_WARNING if result != ACCEPTED else M.MAV_SEVERITY_INFO
            out += self.telemetry.statustext(reason, severity)
        out.append(self.mav.command_ack_encode(command, result, 0, 0, src[0], src[1]))
        return out + after

    def _execute(self, cmd: int, p: tuple[float, ...], now_us: int, stats: NodeStats) -> Reply:
        if cmd == M.MAV_CMD_COMPONENT_ARM_DISARM:  # param2 (ArduPilot's force, 21196) ignored: no bypass
            if p[0] not in (0.0, 1.0):
                return DENIED, f"arm/disarm: param1 must be 0 or 1, got {p[0]:g}", []
            if p[0] == 1.0:
                return _verdict(self.vehicle.arm(), "arm refused")
            return _verdict(self.vehicle.disarm(), "disarm refused")
        if cmd == M.MAV_CMD_DO_SET_MODE:
            return self._set_mode(int(p[0]), int(p[1]))
        if cmd == M.MAV_CMD_DO_SET_STANDARD_MODE:
            return self._set_standard_mode(p[0])
        if cmd == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            return _verdict(self.telemetry.set_interval(int(p[0]), int(p[1])), "message interval refused")
        if cmd == M.MAV_CMD_GET_MESSAGE_INTERVAL:
            msg_id = int(p[0])
            interval = self.telemetry.interval_us(msg_id) if msg_id in STREAMS else 0
            return ACCEPTED, "", [self.mav.message_interval_encode(msg_id, interval if interval > 0 else -1)]
        if cmd == M.MAV_CMD_REQUEST_MESSAGE:
            if int(p[0]) == M.MAVLINK_MSG_ID_AVAILABLE_MODES and p[1] >= 1:  # param2: one mode by index
                code, why, msgs = self._request_message(int(p[0]), now_us, stats)
                return (code, why, msgs[int(p[1]) - 1:int(p[1])]) if p[1] <= len(msgs) else \
                    (DENIED, f"no mode with index {p[1]:g} (1..{len(msgs)})", [])
            return self._request_message(int(p[0]), now_us, stats)
        if cmd == M.MAV_CMD_REQUEST_PROTOCOL_VERSION:
            return self._request_message(MSG_ID_PROTOCOL_VERSION, now_us, stats)
        if cmd == M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return self._request_message(M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, now_us, stats)
        if cmd == M.MAV_CMD_GET_HOME_POSITION:  # deprecated for REQUEST_MESSAGE; MAVProxy still sends it
            return self._request_message(M.MAVLINK_MSG_ID_HOME_POSITION, now_us, stats)
        if cmd == M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            action = int(p[0])
            if action == 0:
                return ACCEPTED, "", []  # "do nothing" for the autopilot
            if action != 1:
                return UNSUPPORTED, "only reboot (param1=1) is supported", []
            if self.vehicle.status().armed:
                return TEMP_REJECTED, "reboot refused: disarm first", []
            return ACCEPTED, "rebooting: reloading params and policy", self._reboot()
        if cmd == M.MAV_CMD_MISSION_START:
            if self.mission.uploading:
                return TEMP_REJECTED, "mission start refused: upload in progress", []
            return _verdict(self.vehicle.start_mission(), "mission start refused")
        if cmd == M.MAV_CMD_DO_SET_MISSION_CURRENT:
            seq = int(p[0])
            if not 0 <= seq < len(self.mission.items):
                return DENIED, f"set mission current refused: no item {seq}", []
            return _verdict(self.vehicle.set_mission_current(seq), "set mission current refused")
        if cmd == CMD_LOCALISE_GLOBAL:
            if p[0] not in (0.0, 1.0):
                return DENIED, f"global localisation: param1 must be 0 (stay put) or 1 (explore), got {p[0]:g}", []
            return _verdict(self.vehicle.localise_global(explore=p[0] == 1.0), "global localisation refused")
        return UNSUPPORTED, "", []

    def _reposition(self, msg: mavlink2.MAVLink_message, now_us: int) -> Reply:
        """MAV_CMD_DO_REPOSITION, the guided go-to (MAVProxy `guided LAT LON ALT`,
        QGroundControl "go to location"): the point becomes the goal in Guided.
        COMMAND_INT: x/y in the command's frame (global: 1e-7 deg around the
        home origin; LOCAL_NED: metres * frames.LOCAL_ITEM_SCALE); COMMAND_LONG: param5/6 in degrees."""
        lat0, lon0 = self.telemetry.params.get("ORIGIN_LAT"), self.telemetry.params.get("ORIGIN_LON")
        if msg.get_type() == "COMMAND_INT":
            if INT32_MAX in (msg.x, msg.y):  # "unchanged": there is no position to keep going to
                return DENIED, "reposition refused: no position given", []
            if msg.frame in LOCAL_FRAMES:
                local, x, y = True, msg.x / mav_frames.LOCAL_ITEM_SCALE, msg.y / mav_frames.LOCAL_ITEM_SCALE
            elif msg.frame in GLOBAL_FRAMES:
                local, x, y = False, msg.x / 1e7, msg.y / 1e7
            else:
                return DENIED, f"reposition refused: frame {msg.frame} unsupported (global or LOCAL_NED)", []
        else:
            if not (math.isfinite(msg.param5) and math.isfinite(msg.param6)):
                return DENIED, "reposition refused: no position given", []
            local, x, y = False, msg.param5, msg.param6
        bad = check_position(local, x, y)
        if bad is not None:
            return DENIED, f"reposition refused: {bad[1]}", []
        if local:
            x_mm, y_mm = mav_frames.ned_m_to_world(x, y)
        else:
            x_mm, y_mm = mav_frames.global_to_world(round(x * 1e7), round(y * 1e7), lat0, lon0)
        code, why = map_bounds_error(self.vehicle.status().map_mm, x_mm, y_mm)
        if code:
            return DENIED, f"reposition refused: {why}", []
        if int(msg.param2) & M.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE and self.vehicle.status().mode != Mode.GUIDED:
            ok, reason = self.vehicle.set_mode(Mode.GUIDED)
            if not ok:
                return DENIED, f"reposition refused: mode Guided: {reason}", []
        ok, reason = self.vehicle.set_goal(x_mm, y_mm)
        if not ok:
            return DENIED, f"reposition refused: {reason}", []
        return ACCEPTED, "", [self.telemetry.position_target((now_us // 1000) & 0xFFFFFFFF, x_mm, y_mm)]

    def _set_mode(self, base_mode: int, custom_mode: int) -> Reply:
        if not base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return DENIED, "mode refused: custom mode flag not set", []
        try:
            mode = Mode(custom_mode)
        except ValueError:
            return DENIED, f"mode refused: unknown mode {custom_mode}", []
        if mode not in SETTABLE_MODES:
            return DENIED, f"mode refused: {mode.name.title()} not supported", []
        return _verdict(self.vehicle.set_mode(mode), f"mode {SETTABLE_MODES[mode]} refused")

    def _set_standard_mode(self, standard: float) -> Reply:
        """MAV_CMD_DO_SET_STANDARD_MODE: the mode with that standard meaning (telemetry.STANDARD_MODES)."""
        modes = [mode for mode, std, _ in STANDARD_MODES if std == standard and std != M.MAV_STANDARD_MODE_NON_STANDARD]
        if not modes:
            have = ", ".join(f"{std} ({SETTABLE_MODES[mode]})" for mode, std, _ in STANDARD_MODES
                             if std != M.MAV_STANDARD_MODE_NON_STANDARD)
            return DENIED, f"standard mode {standard:g} not available (available: {have})", []
        return _verdict(self.vehicle.set_mode(modes[0]), f"mode {SETTABLE_MODES[modes[0]]} refused")

    def _request_message(self, msg_id: int, now_us: int, stats: NodeStats) -> Reply:
        if not self.telemetry.can_build(msg_id):
            return DENIED, f"message {msg_id} not available", []
        msgs = self.telemetry.build(msg_id, now_us, self.vehicle.status(), stats)
        if not msgs:
            return DENIED, f"message {msg_id} has no data now", []
        return ACCEPTED, "", msgs

