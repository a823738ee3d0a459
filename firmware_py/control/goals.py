"""Command-line goals driven from the control thread.

`GoalRunner` is a per-tick callback (`RobotNode.after_tick`): it arms the
vehicle once its inputs are fresh, starts the goal (or the mission of several
goals), and records how the run ended. Running it on the ticking thread keeps
a lockstep run deterministic. Used by `qnav-robot --goal` and by the ground
station's lockstep rigs.
"""

from __future__ import annotations

import logging
import threading

from firmware_py.control.controller import Controller
from firmware_py.control.io import Outputs
from firmware_py.vehicle import CtrlState


class GoalRunner:
    """Arms and starts the command-line goals, and notices when they are done (module docstring)."""

    def __init__(self, ctrl: Controller, goals: list[tuple[int, int]]) -> None:
        self.ctrl = ctrl
        self.goals = goals
        self.started = False
        self.done = threading.Event()
        self.result = ""
        self._last_refusal = ""

    def __call__(self, _out: Outputs) -> None:
        c = self.ctrl
        if not self.started:
            if c.state == CtrlState.STANDBY:
                ok, why = c.arm()
                if not ok:
                    if why != self._last_refusal:
                        logging.getLogger("qnav.robot").info("waiting to arm: %s", why)
                        self._last_refusal = why
                    return
            if c.state != CtrlState.HOLD:
                return
            if len(self.goals) == 1:
                ok, why = c.go_to(*self.goals[0])
            else:
                ok, why = c.set_mission(self.goals)
                if ok:
                    ok, why = c.start_mission()
            if not ok:
                self.result = f"goal refused: {why}"
                self.done.set()
            self.started = True
            return
        if self.done.is_set():
            return
        if c.state == CtrlState.FAULT:
            self.result = f"FAULT: {c.fault}"
            self.done.set()
        elif c.state == CtrlState.HOLD:
            last = c.transitions[-1] if c.transitions else None
            if last is not None and last.cause in ("goal reached", "mission complete"):
                self.result = "reached"
            else:
                self.result = f"stopped: {last.cause if last else '?'}"
            self.done.set()
