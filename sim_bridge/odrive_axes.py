"""Two emulated ODrive axes (CANSimple) driving the plant's wheels.

What an ODrive does on the bus, from its published CANSimple protocol (the same facts as
firmware_py/drives/odrive.py, written again here from the protocol, not imported, so the robot's
backend is tested against an independent reading):

* each axis answers to `node_id << 5 | cmd`: Set_Axis_State (0x07; IDLE 1, CLOSED_LOOP_CONTROL 8,
  refused while an error is set), Set_Controller_Mode (0x0B), Set_Input_Vel (0x0D, turns/s of the
  motor), Clear_Errors (0x18), Estop (0x02);
* it sends a Heartbeat (0x01: Axis_Error u32, Axis_State u8, Procedure_Result u8, Trajectory_Done
  u8) every 100 ms and Get_Encoder_Estimates (0x09: position turns, velocity turns/s, float32) every
  10 ms;
* its watchdog (0.5 s, the expectation ODrive's docs give for CAN control): no Set_Input_Vel for
  that long in closed loop is AXIS_ERROR_WATCHDOG_TIMER_EXPIRED (0x800) and the axis goes IDLE.

The wheels follow the axes through the plant's `MotorDriver` model (first-order response,
acceleration limit): an axis in closed loop commands its wheel, an idle axis commands zero. Motor
turns are the profile's: wheel turns (of its `wheel_radius_mm`) times `gear_ratio`, with the
profile's drive signs; the position estimate is the wheel encoders' measured turns, the velocity the
wheel's speed. Faults to inject: an axis error at a sim time, an axis that falls silent, and a motor
mounted the other way round (`flip`, for bring-up checks).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import can

from firmware_py.profile import RobotProfile
from sim_bridge.motors import MotorDriver

IDLE, CLOSED_LOOP = 1, 8
ERR_WATCHDOG = 0x800
ERR_ESTOP = 0x4000
WATCHDOG_US = 500_000
HEARTBEAT_US = 100_000
ESTIMATES_US = 10_000


@dataclass
class EmulatedAxis:
    node: int
    mount_sign: int  # +1: the motor turning forward drives its wheel forward
    state: int = IDLE
    error: int = 0
    control_mode: int = 0
    input_mode: int = 0
    input_vel: float = 0.0
    last_vel_us: int | None = None
    silent: bool = False
    commands: dict[int, int] = field(default_factory=dict)  # cmd id -> frames received

    def handle(self, cmd: int, data: bytes, now_us: int) -> None:
        self.commands[cmd] = self.commands.get(cmd, 0) + 1
        if cmd == 0x07 and len(data) >= 4:
            want = struct.unpack_from("<I", data)[0]
            if want == CLOSED_LOOP and self.error == 0:
                self.state, self.last_vel_us = CLOSED_LOOP, now_us
            elif want == IDLE:
                self.state, self.input_vel = IDLE, 0.0
        elif cmd == 0x0B and len(data) >= 8:
            self.control_mode, self.input_mode = struct.unpack_from("<II", data)
        elif cmd == 0x0D and len(data) >= 8:
            vel = struct.unpack_from("<f", data)[0]
            if math.isfinite(vel):
                self.input_vel, self.last_vel_us = vel, now_us
        elif cmd == 0x18:
            self.error = 0
        elif cmd == 0x02:
            self.fail(ERR_ESTOP)

    def fail(self, error: int) -> None:
        self.error |= error
        self.state, self.input_vel = IDLE, 0.0

    def check_watchdog(self, now_us: int) -> None:
        if self.state == CLOSED_LOOP and self.last_vel_us is not None and now_us - self.last_vel_us >= WATCHDOG_US:
            self.fail(ERR_WATCHDOG)

    def motor_turns_s(self) -> float:
        """The velocity the axis holds its motor at (turns/s; 0 unless in velocity closed loop)."""
        return self.input_vel if self.state == CLOSED_LOOP and self.control_mode == 2 else 0.0


class ODrivePair:
    """The left and right axes of a robot profile, on the plant's wheels."""

    def __init__(self, profile: RobotProfile, motors: MotorDriver, flip: str = "") -> None:
        d = profile.drive
        self.axes = [EmulatedAxis(d.left_node, d.left_sign * (-1 if flip == "left" else 1)),
                     EmulatedAxis(d.right_node, d.right_sign * (-1 if flip == "right" else 1))]
        self._by_node = {a.node: a for a in self.axes}
        self.motors = motors
        self.gear = d.gear_ratio
        self.mm_per_wheel_turn = profile.wheel_circumference_mm()
        self.out: list[can.Message] = []
        self.faults: list[tuple[int, str, str]] = []  # (sim us, "error:CODE" | "silent", side)

    def owns(self, msg: can.Message) -> bool:
        return (not msg.is_extended_id and not msg.is_error_frame and (msg.arbitration_id >> 5) in self._by_node
                and (msg.arbitration_id & 0x1F) in (0x02, 0x07, 0x0B, 0x0D, 0x18))

    def handle(self, msg: can.Message, now_us: int) -> None:
        axis = self._by_node[msg.arbitration_id >> 5]
        axis.handle(msg.arbitration_id & 0x1F, bytes(msg.data), now_us)
        self._command_wheels(now_us)

    def _command_wheels(self, now_us: int) -> None:
        speeds = [a.mount_sign * a.motor_turns_s() / self.gear * self.mm_per_wheel_turn for a in self.axes]
        self.motors.command(round(speeds[0]), round(speeds[1]), 0, now_us)

    def step(self, now_us: int, wheel_turns: tuple[float, float]) -> None:
        """After a physics step at sim time `now_us`: faults due, watchdogs, and the frames due now
        (`wheel_turns`: each wheel's measured turns, `WheelEncoders.wheel_turns`)."""
        for t, what, side in list(self.faults):
            if now_us >= t:
                self.faults.remove((t, what, side))
                axis = self.axes[0 if side == "left" else 1]
                if what == "silent":
                    axis.silent = True
                else:
                    axis.fail(int(what.split(":")[1], 0))
        for a in self.axes:
            a.check_watchdog(now_us)
        self._command_wheels(now_us)
        for a, turns, speed in zip(self.axes, wheel_turns, self.motors.speed, strict=True):
            if a.silent:
                continue
            if now_us % ESTIMATES_US == 0:
                pos = a.mount_sign * turns * self.gear
                vel = a.mount_sign * speed / self.mm_per_wheel_turn * self.gear
                self.out.append(can.Message(arbitration_id=a.node << 5 | 0x09, is_extended_id=False,
                                            data=struct.pack("<ff", pos, vel)))
            if now_us % HEARTBEAT_US == 0:
                self.out.append(can.Message(arbitration_id=a.node << 5 | 0x01, is_extended_id=False,
                                            data=struct.pack("<IBBBB", a.error, a.state, 0, 0, 0)[:8]))

    def drain(self) -> list[can.Message]:
        out, self.out = self.out, []
        return out
