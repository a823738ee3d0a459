"""The controller's record of its state machine: the severities it reports with, the transition
log (`Controller.transitions`: time, from, to, cause; logged, warning level for safety causes) and
the queue of events the MAVLink node turns into STATUSTEXT (`drain`).
"""

from __future__ import annotations

import logging
from collections import deque

from firmware_py.control.io import Transition
from firmware_py.vehicle import CtrlState, VehicleEvent

log = logging.getLogger("qnav.controller")

SEV_CRITICAL = 2
SEV_ERROR = 3
SEV_WARNING = 4
SEV_NOTICE = 5
SEV_INFO = 6


class StateLog:
    """Transitions and events, as recorded (module docstring)."""

    def __init__(self) -> None:
        self.transitions: deque[Transition] = deque(maxlen=1024)
        self.events: deque[VehicleEvent] = deque(maxlen=256)

    def event(self, kind: str, text: str, severity: int = SEV_INFO, seq: int = -1) -> None:
        self.events.append(VehicleEvent(kind=kind, text=text[:50], seq=seq, severity=severity))

    def transition(self, now_us: int, src: CtrlState, dst: CtrlState, cause: str, severity: int) -> None:
        self.transitions.append(Transition(now_us, src, dst, cause))
        log.log(logging.WARNING if severity <= SEV_WARNING else logging.INFO,
                "t=%d us %s -> %s: %s", now_us, src.name, dst.name, cause)
        self.event("transition", f"{src.name}->{dst.name}: {cause}", severity)

    def drain(self) -> list[VehicleEvent]:
        out = list(self.events)
        self.events.clear()
        return out
