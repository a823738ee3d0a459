"""The extension seam of `qnav-robot`: what an add-on (the MAVLink shell) sees.

`qnav-robot` (firmware_py.cli) builds the control node and hands it to each extension as a
`ControlNode`: the vehicle seam (`controller`), the node's clock and the list of per-tick callbacks.
Extensions never import the control package, so `firmware_py.control` and `firmware_py.mavlink` meet
only through `firmware_py.vehicle`. Also owns the robot program's exit codes and its one-line usage
error.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any, Protocol

from firmware_py.clock import Clock
from firmware_py.vehicle import VehicleControl

EXIT_OK = 0
EXIT_USAGE = 2
EXIT_FAULT = 3
EXIT_TIMEOUT = 4


class UsageError(Exception):
    """Bad command-line input; printed as one line, exit 2."""


class ControlNode(Protocol):
    """The running control node as an extension sees it."""

    @property
    def controller(self) -> VehicleControl: ...
    @property
    def clock(self) -> Clock: ...
    @property
    def after_tick(self) -> list[Callable[[Any], None]]: ...


class Extension(Protocol):
    def add_arguments(self, parser: argparse.ArgumentParser) -> None: ...
    def attach(self, node: ControlNode, args: argparse.Namespace) -> Callable[[], None] | None: ...
