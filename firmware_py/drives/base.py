"""The drive backend contract (see firmware_py/drives/__init__.py)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, NamedTuple

import can

from firmware_py.control.io import Outputs


class InputUpdate(NamedTuple):
    """Fields of `Inputs` to set, stamped as input `key` ("enc", "driver") on arrival."""

    key: str
    fields: dict[str, Any]


class DriveBackend(ABC):
    """Wheel speeds out, odometry and motor health in, over the robot's CAN bus."""

    name = "?"
    # in lockstep HIL the tick's last frame answers the sim's SimTick: qnav's MotorCommand carries
    # the tick counter itself; other backends' frames cannot, so the node sends a SimTickAck after them
    answers_lockstep = False

    @abstractmethod
    def take(self, msg: can.Message, now_us: int) -> list[InputUpdate] | None:
        """None when `msg` is not one of this backend's frames; else the input updates it makes."""

    @abstractmethod
    def frames(self, out: Outputs, now_us: int) -> list[can.Message]:
        """The frames of one control tick (wheel command, state requests)."""

    def check(self, now_us: int, timeout_us: int) -> list[InputUpdate]:
        """Per-tick updates that depend on time alone (a board gone silent); default none."""
        return []

    def stats(self) -> dict[str, Any]:
        return {}
