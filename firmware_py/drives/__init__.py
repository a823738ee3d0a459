"""Drive backends: how the controller's wheel speeds reach the motors and how the motors'
odometry and health come back, chosen by name in the robot profile (`[drive] backend`).

A backend is small, like python-can's `BusABC`: `take` turns a frame of its own into
input updates in the controller's vocabulary (`firmware_py.control.io.Inputs` fields),
`frames` turns one tick's `Outputs` into the frames it sends, `check` reports what went
silent. The controller never sees a backend's frames; the node (control/node.py) asks
the backend first and falls back to qnav's own frames.

    qnav      qnav's MotorCommand / MotorStatus / EncoderCounts (qnav.dbc): the default, the sim's
    odrive    two ODrive axes over CANSimple (drives/odrive.py)
"""

from __future__ import annotations

from firmware_py.drives.base import DriveBackend, InputUpdate
from firmware_py.profile import RobotProfile


def open_drive(profile: RobotProfile) -> DriveBackend:
    """The drive backend the profile names."""
    backend = profile.drive.backend
    if backend == "odrive":
        from firmware_py.drives.odrive import ODriveDrive
        return ODriveDrive(profile)
    if backend == "qnav":
        from firmware_py.drives.qnav import QnavDrive
        return QnavDrive(profile)
    raise ValueError(f"drive backend {backend!r} is not available in this build")


__all__ = ["DriveBackend", "InputUpdate", "open_drive"]
