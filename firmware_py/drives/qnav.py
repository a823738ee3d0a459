"""The `qnav` drive backend: qnav's own motor driver frames (qnav.dbc), the default.

MotorStatus and EncoderCounts are decoded by the node with the other qnav frames
(one decoder for the whole DBC), so `take` claims nothing; `frames` is the
MotorCommand, whose counter answers the sim's SimTick in lockstep.
"""

from __future__ import annotations

import can

from firmware_py import can_protocol as proto
from firmware_py.control.io import Outputs
from firmware_py.drives.base import DriveBackend, InputUpdate
from firmware_py.profile import RobotProfile


class QnavDrive(DriveBackend):
    name = "qnav"
    answers_lockstep = True

    def __init__(self, profile: RobotProfile) -> None:
        self.profile = profile

    def take(self, msg: can.Message, now_us: int) -> list[InputUpdate] | None:
        return None

    def frames(self, out: Outputs, now_us: int) -> list[can.Message]:
        if out.motor is None:
            return []
        m = out.motor
        return [proto.motor_command(m.left_mm_s, m.right_mm_s, m.counter)]
