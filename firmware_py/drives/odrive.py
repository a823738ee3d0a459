"""The `odrive` drive backend: two ODrive axes over CANSimple.

Facts from ODrive's published CANSimple protocol (odrive-cansimple.dbc): frame id
`node_id << 5 | cmd_id`, 11-bit, little-endian payloads.

    0x01 Heartbeat              axis -> us   Axis_Error u32, Axis_State u8, ...
    0x07 Set_Axis_State         us -> axis   Axis_Requested_State u32 (1 IDLE, 8 CLOSED_LOOP_CONTROL)
    0x09 Get_Encoder_Estimates  axis -> us   Pos_Estimate f32 turns, Vel_Estimate f32 turns/s
    0x0B Set_Controller_Mode    us -> axis   Control_Mode u32 (2 VELOCITY), Input_Mode u32 (1 PASSTHROUGH)
    0x0D Set_Input_Vel          us -> axis   Input_Vel f32 turns/s, Input_Torque_FF f32 Nm
    0x18 Clear_Errors           us -> axis

What the robot does with them (closed loop while the controller wants the wheels powered,
Set_Input_Vel every tick, zero then IDLE when it stops, Clear_Errors at start and on disarm,
odometry from the encoder estimates, health from the heartbeats): docs/robot-profile.md,
"The `odrive` drive backend".

Pure stdlib + python-can Message; no thread of its own.
"""

from __future__ import annotations

import math
import struct
import threading
from typing import Any

import can

from firmware_py import can_protocol as proto
from firmware_py.control.io import Outputs
from firmware_py.drives.base import DriveBackend, InputUpdate
from firmware_py.profile import RobotProfile

HEARTBEAT = 0x01
SET_AXIS_STATE = 0x07
GET_ENCODER_ESTIMATES = 0x09
SET_CONTROLLER_MODE = 0x0B
SET_INPUT_VEL = 0x0D
CLEAR_ERRORS = 0x18

AXIS_IDLE = 1
AXIS_CLOSED_LOOP = 8
AXIS_STATE_NAMES = {0: "UNDEFINED", 1: "IDLE", 2: "STARTUP_SEQUENCE", 3: "FULL_CALIBRATION_SEQUENCE",
                    4: "MOTOR_CALIBRATION", 6: "ENCODER_INDEX_SEARCH", 7: "ENCODER_OFFSET_CALIBRATION",
                    8: "CLOSED_LOOP_CONTROL"}
CONTROL_VELOCITY = 2
INPUT_PASSTHROUGH = 1
# ODrive 0.5 axis error bits (the heartbeat's Axis_Error)
AXIS_ERROR_NAMES = {0x1: "INVALID_STATE", 0x40: "MOTOR_FAILED", 0x80: "SENSORLESS_ESTIMATOR_FAILED",
                    0x100: "ENCODER_FAILED", 0x200: "CONTROLLER_FAILED", 0x800: "WATCHDOG_TIMER_EXPIRED",
                    0x1000: "MIN_ENDSTOP_PRESSED", 0x2000: "MAX_ENDSTOP_PRESSED", 0x4000: "ESTOP_REQUESTED",
                    0x20000: "HOMING_WITHOUT_ENDSTOP", 0x40000: "OVER_TEMP", 0x80000: "UNKNOWN_POSITION"}

CONFIRM_US = 1_000_000  # closed loop shown in the heartbeat within this of the request
REREQUEST_US = 200_000

_U32 = struct.Struct("<I")
_U32U32 = struct.Struct("<II")
_FF = struct.Struct("<ff")
_HB = struct.Struct("<IB")


def frame_id(node: int, cmd: int) -> int:
    return node << 5 | cmd


def describe_error(error: int) -> str:
    names = [n for bit, n in AXIS_ERROR_NAMES.items() if error & bit]
    return f"0x{error:x}" + (f" ({'|'.join(names)})" if names else "")


class _Axis:
    def __init__(self, side: str, index: int, node: int, sign: int) -> None:
        self.side, self.index, self.node, self.sign = side, index, node, sign
        self.error = 0
        self.state: int | None = None
        self.hb_us: int | None = None
        self.hb_new = False
        self.pos: float | None = None
        self.est_us: int | None = None
        self.est_new = False
        self.confirmed = False  # closed loop seen in a heartbeat since it was last requested

    def name(self) -> str:
        return f"{self.side} axis {self.index} (ODrive node {self.node})"

    def state_name(self) -> str:
        return "none heard" if self.state is None else AXIS_STATE_NAMES.get(self.state, str(self.state))


class ODriveDrive(DriveBackend):
    name = "odrive"

    def __init__(self, profile: RobotProfile) -> None:
        d = profile.drive
        self.axes = [_Axis("left", 0, d.left_node, d.left_sign), _Axis("right", 1, d.right_node, d.right_sign)]
        self._by_node = {a.node: a for a in self.axes}
        self.motor_turns_per_mm = d.gear_ratio / profile.wheel_circumference_mm()
        self.counts_per_motor_turn = profile.geometry.encoder_counts_per_rev / d.gear_ratio
        self.enabled = False
        self.requested_us = 0
        self.last_request_us = 0
        self.bad_frames = 0
        self.frames_sent = 0
        # an axis error stays until Clear_Errors, and the controller will not arm over one: errors are
        # cleared once at start and on each disarm (the operator's acknowledgement, as ArduPilot's)
        self._clear_pending = True
        self._was_armed = False
        self._lock = threading.Lock()

    # --- frames in ---------------------------------------------------------------
    def take(self, msg: can.Message, now_us: int) -> list[InputUpdate] | None:
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            return None
        axis = self._by_node.get(msg.arbitration_id >> 5)
        cmd = msg.arbitration_id & 0x1F
        if axis is None or cmd not in (HEARTBEAT, GET_ENCODER_ESTIMATES):
            return None
        with self._lock:
            if cmd == HEARTBEAT:
                if len(msg.data) < _HB.size:
                    self.bad_frames += 1
                    return []
                axis.error, axis.state = _HB.unpack_from(bytes(msg.data))
                axis.hb_us, axis.hb_new = now_us, True
                if axis.state == AXIS_CLOSED_LOOP and self.enabled:
                    axis.confirmed = True
                if all(a.hb_new for a in self.axes) or axis.error:
                    for a in self.axes:
                        a.hb_new = False
                    return [InputUpdate("driver", self._driver_fields(now_us))]
                return []
            if len(msg.data) < _FF.size:
                self.bad_frames += 1
                return []
            pos, vel = _FF.unpack_from(bytes(msg.data))
            if not (math.isfinite(pos) and math.isfinite(vel)) or abs(pos) > 1e9:
                self.bad_frames += 1
                return []
            axis.pos, axis.est_new, axis.est_us = pos, True, now_us  # vel: checked, not used
            if not all(a.est_new for a in self.axes):
                return []
            for a in self.axes:
                a.est_new = False
            left, right = (self._counts(a) for a in self.axes)
            return [InputUpdate("enc", {"enc_left": left, "enc_right": right})]

    def _counts(self, a: _Axis) -> int:
        return proto.wrap_counts(round(a.sign * (a.pos or 0.0) * self.counts_per_motor_turn))

    def _trouble(self, now_us: int) -> str:
        """What is wrong with the axes now ('' when nothing): errors, closed loop lost or never reached."""
        for a in self.axes:
            if a.error:
                return f"{a.name()}: axis error {describe_error(a.error)}, state {a.state_name()}"
        if self.enabled:
            for a in self.axes:
                if a.confirmed and a.state != AXIS_CLOSED_LOOP:
                    return f"{a.name()} left closed loop: state {a.state_name()}"
                if not a.confirmed and now_us - self.requested_us > CONFIRM_US:
                    return (f"{a.name()} did not enter closed loop within {CONFIRM_US / 1e6:g} s: "
                            f"state {a.state_name()}")
        return ""

    def _driver_fields(self, now_us: int) -> dict[str, Any]:
        trouble = self._trouble(now_us)
        running = all(a.state == AXIS_CLOSED_LOOP for a in self.axes)
        return {"driver_state": proto.MOTOR_RUNNING if running else proto.MOTOR_IDLE,
                "driver_errors": sum(1 << a.index for a in self.axes if a.error) or (4 if trouble else 0),
                "driver_detail": trouble, "driver_estop": False}

    def check(self, now_us: int, timeout_us: int) -> list[InputUpdate]:
        with self._lock:
            fields = self._driver_fields(now_us)
            if not fields["driver_detail"]:
                silent = [(a, what, t) for a in self.axes for what, t in (("heartbeat", a.hb_us),
                                                                          ("encoder estimates", a.est_us))
                          if t is None or now_us - t > timeout_us]
                if silent:
                    a, what, t = silent[0]
                    since = f"no {what} for {(now_us - t) // 1000} ms" if t is not None else f"no {what} heard"
                    fields["driver_detail"] = f"{a.name()}: {since}"
            # time-dependent troubles become errors now; silence shows as the "driver" stamp going stale
            return [InputUpdate("", {"driver_errors": fields["driver_errors"], "driver_detail": fields["driver_detail"]})]

    # --- frames out --------------------------------------------------------------
    def frames(self, out: Outputs, now_us: int) -> list[can.Message]:
        with self._lock:
            want = out.drive_enabled and out.motor is not None
            msgs: list[can.Message] = []
            armed = out.heartbeat.armed
            clear = (self._was_armed and not armed) or self._clear_pending
            self._clear_pending, self._was_armed = False, armed
            if want and not self.enabled:
                self.enabled, self.requested_us, self.last_request_us = True, now_us, now_us
                for a in self.axes:
                    a.confirmed = False
                    msgs.append(self._msg(a, CLEAR_ERRORS, b""))
                    msgs.append(self._msg(a, SET_CONTROLLER_MODE, _U32U32.pack(CONTROL_VELOCITY, INPUT_PASSTHROUGH)))
                    msgs.append(self._msg(a, SET_AXIS_STATE, _U32.pack(AXIS_CLOSED_LOOP)))
            elif want and not all(a.confirmed for a in self.axes) and now_us - self.last_request_us >= REREQUEST_US:
                self.last_request_us = now_us
                msgs += [self._msg(a, SET_AXIS_STATE, _U32.pack(AXIS_CLOSED_LOOP)) for a in self.axes if not a.confirmed]
            if want:
                assert out.motor is not None
                speeds = (out.motor.left_mm_s, out.motor.right_mm_s)
                for a in self.axes:
                    vel = a.sign * speeds[a.index] * self.motor_turns_per_mm if a.confirmed else 0.0
                    msgs.append(self._msg(a, SET_INPUT_VEL, _FF.pack(vel, 0.0)))
            elif self.enabled:  # stop: zero velocity, then unpower
                self.enabled = False
                msgs += [self._msg(a, SET_INPUT_VEL, _FF.pack(0.0, 0.0)) for a in self.axes]
                msgs += [self._msg(a, SET_AXIS_STATE, _U32.pack(AXIS_IDLE)) for a in self.axes]
                for a in self.axes:
                    a.confirmed = False
            if clear:  # after the stop: the error is acknowledged once the axis is idle
                msgs += [self._msg(a, CLEAR_ERRORS, b"") for a in self.axes]
            self.frames_sent += len(msgs)
            return msgs

    @staticmethod
    def _msg(a: _Axis, cmd: int, data: bytes) -> can.Message:
        return can.Message(arbitration_id=frame_id(a.node, cmd), data=data, is_extended_id=False)

    def stats(self) -> dict[str, Any]:
        return {"drive_bad_frames": self.bad_frames, "drive_frames_sent": self.frames_sent}
