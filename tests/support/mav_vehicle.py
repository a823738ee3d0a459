"""A small but real vehicle state machine implementing `VehicleControl`.

Used by the MAVLink tests until/besides the real controller: it arms,
disarms, switches modes, drives straight at a goal at a fixed speed when
`step()` is called, walks a mission in Auto and reports every transition as
an event, exactly through the seam the node uses. Not a protocol mock: the
MAVLink side under test is the real node. `Robot` runs it behind the real
node shell on a UDP port, ticking in a thread.
"""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

from firmware_py import robot_spec
from firmware_py.clock import SimClock
from firmware_py.mavlink.node import open_node
from firmware_py.vehicle import (
    CtrlState,
    FailsafeAction,
    Mode,
    VehicleConfig,
    VehicleEvent,
    VehicleStatus,
)
from tests.support.sim_time import advance_us


class TestVehicle:
    __test__ = False  # not a pytest class

    def __init__(self, speed_mm_s: int = 400) -> None:
        self.cfg = VehicleConfig()
        self.st = VehicleStatus(state=CtrlState.STANDBY, mode=Mode.HOLD, sensors_healthy=True, motors_healthy=True)
        self.mission: list[tuple[int, int]] = []
        self.events: list[VehicleEvent] = []
        self.speed = speed_mm_s
        self.config_applied = 0
        self.failsafe_calls: list[bool] = []
        self.manual_samples: list[tuple[int, int, int]] = []
        self.refuse_arm = ""  # set to make arm() refuse with this reason

    # --- helpers ------------------------------------------------------------------
    def _event(self, kind: str, text: str, seq: int = -1, severity: int = 6) -> None:
        self.events.append(VehicleEvent(kind, text, seq, severity))

    def _state(self, state: CtrlState, cause: str) -> None:
        if state != self.st.state:
            self._event("transition", f"{self.st.state.name}->{state.name}: {cause}")
            self.st.state = state

    def _drive_to(self, goal: tuple[int, int] | None, cause: str) -> None:
        self.st.goal_mm = goal
        if goal is None:
            self._state(CtrlState.HOLD if self.st.armed else CtrlState.STANDBY, cause)
        elif self.st.armed:
            self._state(CtrlState.DRIVING, cause)

    # --- VehicleControl ---------------------------------------------------------------
    def status(self) -> VehicleStatus:
        self.st.mission_count = len(self.mission)
        return self.st

    def localise_global(self, explore: bool = True) -> tuple[bool, str]:
        return False, "no map: the active policy carries none (qnav policy attach-map)"

    def arm(self) -> tuple[bool, str]:
        if self.refuse_arm:
            return False, self.refuse_arm
        if self.st.state == CtrlState.FAULT:
            return False, "in FAULT"
        self.st.armed = True
        self._state(CtrlState.DRIVING if self.st.goal_mm and self.st.mode != Mode.HOLD else CtrlState.HOLD, "armed")
        return True, ""

    def disarm(self) -> tuple[bool, str]:
        self.st.armed = False
        self.st.speed_mm_s = 0
        self._state(CtrlState.STANDBY, "disarmed")
        return True, ""

    def set_mode(self, mode: Mode) -> tuple[bool, str]:
        if mode == Mode.AUTO and not self.mission:
            return False, "no mission"
        if self.st.failsafe and mode != Mode.HOLD:
            return False, "GCS failsafe active"
        self.st.mode = mode
        self._event("transition", f"mode {mode.name}")
        if mode == Mode.HOLD:
            self._drive_to(None, "mode Hold")
        elif mode == Mode.AUTO:
            self._drive_to(self.mission[self.st.mission_seq], "mode Auto")
        return True, ""

    def set_goal(self, x_mm: int, y_mm: int) -> tuple[bool, str]:
        if self.st.mode != Mode.GUIDED:
            return False, "not in Guided"
        self._drive_to((x_mm, y_mm), "new goal")
        return True, ""

    def set_mission(self, waypoints_mm: list[tuple[int, int]]) -> tuple[bool, str]:
        if self.st.mode == Mode.AUTO and self.st.armed:
            return False, "mission running"
        self.mission = list(waypoints_mm)
        self.st.mission_seq = 0
        return True, ""

    def set_mission_current(self, seq: int) -> tuple[bool, str]:
        if not 0 <= seq < len(self.mission):
            return False, f"no item {seq}"
        self.st.mission_seq = seq
        if self.st.mode == Mode.AUTO:
            self._drive_to(self.mission[seq], "mission current set")
        return True, ""

    def start_mission(self) -> tuple[bool, str]:
        if not self.st.armed:
            return False, "not armed"
        if not self.mission:
            return False, "no mission"
        self.st.mission_seq = 0
        return self.set_mode(Mode.AUTO)

    def manual_control(self, x: int, r: int, now_us: int) -> bool:
        self.manual_samples.append((x, r, now_us))
        return True

    def set_failsafe(self, active: bool) -> None:
        self.failsafe_calls.append(active)
        self.st.failsafe = active
        if active and self.cfg.gcs_failsafe_action == FailsafeAction.HOLD:
            self.st.mode = Mode.HOLD
            self._drive_to(None, "GCS failsafe")
        elif active and self.cfg.gcs_failsafe_action == FailsafeAction.DISARM:
            self.disarm()

    def check_config(self, cfg: VehicleConfig) -> tuple[bool, str]:
        return True, ""  # runs no policy, so any config fits

    def apply_config(self, cfg: VehicleConfig) -> None:
        self.cfg = cfg
        self.config_applied += 1

    def activate_policy(self, path: str) -> tuple[bool, str]:
        return False, "the test vehicle runs no policy"

    def drain_events(self) -> list[VehicleEvent]:
        out, self.events = self.events, []
        return out

    # --- plant ------------------------------------------------------------------------
    def step(self, dt_us: int) -> None:
        """Drive straight at the goal for dt_us (a kinematic stand-in for the sim)."""
        st = self.st
        st.time_us += dt_us
        if st.state != CtrlState.DRIVING or st.goal_mm is None:
            st.speed_mm_s = 0
            return
        dx, dy = st.goal_mm[0] - st.x_mm, st.goal_mm[1] - st.y_mm
        dist = math.hypot(dx, dy)
        st.heading_mrad = round(math.atan2(dy, dx) * 1000)
        st.distance_to_goal_mm = round(dist)
        st.bearing_to_goal_mrad = 0
        if dist <= self.cfg.goal_tolerance_mm:
            st.speed_mm_s = 0
            self._state(CtrlState.GOAL_REACHED, "goal reached")
            if st.mode == Mode.AUTO:
                self._event("mission_item_reached", f"reached item {st.mission_seq}", st.mission_seq)
                if st.mission_seq + 1 < len(self.mission):
                    st.mission_seq += 1
                    self._drive_to(self.mission[st.mission_seq], "next item")
                else:
                    st.goal_mm = None
                    self._state(CtrlState.HOLD, "mission complete")
            else:
                st.goal_mm = None
                self._state(CtrlState.HOLD, "goal reached")
            return
        move = min(dist, self.speed * dt_us / 1e6)
        st.x_mm += round(dx / dist * move)
        st.y_mm += round(dy / dist * move)
        st.speed_mm_s = self.speed


class Robot:
    """The node shell + test vehicle, ticking once per control period like
    the controller's loop calls `poll`. The robot clock is a SimClock moved
    one control period per tick (paced at about real time), as in HIL."""

    def __init__(self, storage: Path, port: int, key_file: Path | None = None, speed_mm_s: int = 10_000) -> None:
        self.clock = SimClock(1_000_000)
        self.vehicle = TestVehicle(speed_mm_s=speed_mm_s)
        self.shell = open_node(self.vehicle, storage, f"udpout:127.0.0.1:{port}", self.clock.now_us(),
                               signing_key=str(key_file) if key_file else None)
        self.node = self.shell.node
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        period = robot_spec.CONTROL_PERIOD_US
        next_t = time.monotonic()
        while not self._stop.is_set():
            with self._lock:
                advance_us(self.clock, period)
                self.vehicle.step(period)
                self.shell.poll(self.clock.now_us())
            next_t += period / 1e6
            time.sleep(max(0.0, next_t - time.monotonic()))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.shell.close()
