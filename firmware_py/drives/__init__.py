"""Drive backends: how the controller's wheel speeds reach the motors and how the motors'
odometry and health come back, chosen by name in the robot profile (`[drive] backend`).

A backend is small, like python-can's `BusABC`: `take` turns a frame of its own into
input updates in the controller's vocabulary (`firmware_py.control.io.Inputs` fields),
`frames` turns one tick's `Outputs` into the frames it sends, `check` reports what went
silent. The controller never sees a backend's frames; the node (control/node.py) asks
the backend first and falls back to qnav's own frames.

    qnav      qnav's MotorCommand / MotorStatus / EncoderCounts (qnav.dbc): the default, the sim's
    odrive    two ODrive axes over CANSimple (drives/odrive.py)
    dronecan  DroneCAN ESCs and/or rangefinders, the robot as a DroneCAN node (drives/dronecan.py;
              the `dronecan` extra); chosen separately for the drive and the sensors
"""

from __future__ import annotations

from typing import Any

import can

from firmware_py.control.io import Outputs
from firmware_py.drives.base import DriveBackend, InputUpdate
from firmware_py.profile import RobotProfile


def open_drive(profile: RobotProfile) -> DriveBackend:
    """The backends the profile names, as one (the drive's frames last: in lockstep HIL qnav's
    MotorCommand is the tick's answer). ValueError (one line) when one cannot be had here."""
    drive, sensors = profile.drive.backend, profile.sensors.backend
    parts: list[DriveBackend] = []
    if drive == "dronecan" or sensors == "dronecan":
        try:
            from firmware_py.drives.dronecan import DroneCanBackend
        except ImportError:  # `pip install qnav` alone: the robot without the optional extra
            raise ValueError("the dronecan backends need the dronecan library: pip install 'qnav[dronecan]'") from None
        parts.append(DroneCanBackend(profile, drive=drive == "dronecan", sensors=sensors == "dronecan"))
    if drive == "odrive":
        from firmware_py.drives.odrive import ODriveDrive
        parts.append(ODriveDrive(profile))
    elif drive == "qnav":
        from firmware_py.drives.qnav import QnavDrive
        parts.append(QnavDrive(profile))
    if len(parts) == 1:
        return parts[0]
    return Composite(parts, answers_lockstep=drive == "qnav", name=f"{drive}+{sensors} sensors")


class Composite(DriveBackend):
    """Several backends on one bus: a frame goes to the first that claims it; frames out in order."""

    def __init__(self, parts: list[DriveBackend], *, answers_lockstep: bool, name: str) -> None:
        self.parts = parts
        self.answers_lockstep = answers_lockstep
        self.name = name

    def take(self, msg: can.Message, now_us: int) -> list[InputUpdate] | None:
        for part in self.parts:
            updates = part.take(msg, now_us)
            if updates is not None:
                return updates
        return None

    def frames(self, out: Outputs, now_us: int) -> list[can.Message]:
        return [f for part in self.parts for f in part.frames(out, now_us)]

    def check(self, now_us: int, timeout_us: int) -> list[InputUpdate]:
        return [u for part in self.parts for u in part.check(now_us, timeout_us)]

    def stats(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for part in self.parts:
            out.update(part.stats())
        return out


__all__ = ["DriveBackend", "InputUpdate", "open_drive"]
