"""The controller's state and the primitives every part of it changes it with:
transitions (logged, queued as events), stop, fault, the active policy's kind
at work and its localiser, the pose the robot drives by, starting a drive.
`firmware_py.control.controller.Controller` builds on it with the
VehicleControl commands and the tick.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from typing import Any

from firmware_py import kinds
from firmware_py.background import Background
from firmware_py.can_protocol import ENCODER_BITS
from firmware_py.control.explore import Exploration
from firmware_py.control.io import (
    Inputs,
    Transition,
)
from firmware_py.control.localiser import Localiser, LocaliserConfig
from firmware_py.control.manual import ManualSticks
from firmware_py.control.odometry import Odometry
from firmware_py.control.plausibility import InputFreshness
from firmware_py.control.progress import ProgressWatch, StallWatch
from firmware_py.control.route import Route
from firmware_py.control.safety import EStopLatch, MotorWatchdog
from firmware_py.kinds import KindDriver
from firmware_py.policy import Policy
from firmware_py.vehicle import (
    CtrlState,
    Mode,
    VehicleConfig,
    VehicleEvent,
)

log = logging.getLogger("qnav.controller")

SEV_CRITICAL = 2
SEV_ERROR = 3
SEV_WARNING = 4
SEV_NOTICE = 5
SEV_INFO = 6

STOP_BURST_TICKS = 3  # zero commands sent after leaving DRIVING when not in lockstep


class ControlState:
    """The controller's state and the primitives that change it (module docstring)."""

    def __init__(self, config: VehicleConfig | None = None, policy: Policy | None = None, *,
                 start_pose_mm: tuple[int, int, int] = (0, 0, 0), lockstep: bool = False,
                 localise: bool = True, localiser_config: LocaliserConfig | None = None,
                 profile: Any = None) -> None:
        self.cfg = config or VehicleConfig()
        self._lock = threading.RLock()
        self.lockstep = lockstep
        # the active kind's off-tick work (the local planner's search): stepped by the node between
        # lockstep ticks (reproducible runs), a worker thread otherwise (firmware_py.background)
        self.background = Background(threaded=not lockstep)
        # the robot's own map (qnav-robot --map FILE; mapdata.OccupancyGrid): a policy carrying another is
        # refused at boot and activation (policy.config_mismatch). None: the policy's map is taken as is
        self.robot_map: Any = None
        # qnav-robot --profile (firmware_py.profile.RobotProfile; None: the built-in robot): its geometry
        # drives odometry, and a policy trained for another is refused (policy.config_mismatch)
        self.robot_profile: Any = profile
        self._corners: Any = None  # the collision monitor's index of that map's block corners (collision.MapCorners)
        self.policy = policy
        self.last_known_good: Policy | None = None
        g = profile.geometry if profile is not None else None
        self.odom = Odometry(*start_pose_mm, counter_bits=ENCODER_BITS) if g is None else Odometry(
            *start_pose_mm, ticks_per_rev=g.encoder_counts_per_rev, wheel_radius_mm=g.wheel_radius_mm,
            wheel_base_mm=g.wheel_base_mm, counter_bits=ENCODER_BITS)
        self.watchdog = MotorWatchdog(self.cfg.motor_timeout_ms * 1000)
        self.estop_latch = EStopLatch()
        self.state = CtrlState.BOOT
        self.mode = Mode.HOLD
        self.armed = False
        self.failsafe = False
        self.fault = ""
        self.goal: tuple[int, int] | None = None
        self._goal_index = 0
        self.route = Route()  # the mission and its item in force
        self._events: deque[VehicleEvent] = deque(maxlen=256)
        self.progress = ProgressWatch()  # STATUSTEXT when the way is blocked
        self.stall = StallWatch()  # a drive getting nowhere for NAV_STALL_S: reported and held
        self.transitions: deque[Transition] = deque(maxlen=1024)
        self._now = 0
        self._inputs = Inputs()
        self._last_enc_us: int | None = None
        self.encoder_jumps = 0  # implausible encoder samples (not integrated)
        self.collision_ticks = {"slow": 0, "stop": 0}  # commands the collision monitor limited
        self._cm_stop_since_us: int | None = None  # the monitor has removed the straight part since
        self.freshness = InputFreshness()  # rolling counters: frozen senders
        self._stop_burst = 0
        self._driving_since_us = 0
        self._cmd_counter = 0
        self._hb_counter = 0
        self._ticks = 0
        self._errors = 0
        self._state_index = -1
        self._action = -1
        self._q_row: tuple[int, ...] = ()
        # the active policy's kind at work (firmware_py.kinds): its decisions and its memory
        self.driver: KindDriver | None = kinds.of_policy(policy).driver(policy, self.background) if policy is not None else None
        self.target_mm: tuple[int, int] | None = None  # what the policy steered to (None: the goal itself)
        self.tick_overruns = 0
        self.can_errors = 0
        # Monte Carlo localisation on the policy's map (control/localiser.py) when the policy carries one
        self.localise = localise
        self._loc_cfg = localiser_config
        self.loc: Localiser | None = None
        self.exploration = Exploration()  # the wander for global localisation (armed, HOLD)
        self.manual = ManualSticks()  # Manual mode's sticks and deadman (control/manual.py)
        self._manual_was_driving = False
        self._arm_block = ""  # the last backend arming block reported (controller.step says a new one once)
        self._use_localiser(policy, self._new_localiser(policy))

    # --- helpers ------------------------------------------------------------------
    def _new_localiser(self, pol: Policy | None) -> Localiser | None:
        """A localiser for `pol`'s map when the running one is for another map
        (None: keep the running one, or there is no map). Building one
        precomputes its likelihood field (~0.1-0.5 s for paper10), so it runs
        outside the lock: the ticks keep going."""
        grid = pol.map_grid if pol is not None and self.localise else None
        cur = self.loc
        if grid is None or (cur is not None and cur.grid == grid):
            return None
        return Localiser(grid, self._loc_cfg)

    def _use_localiser(self, pol: Policy | None, new: Localiser | None) -> None:
        """Under the lock: switch to `new` (started at the odometry pose), keep
        the running one for the same map, or drop it (no map: odometry alone)."""
        if pol is None or pol.map_grid is None or not self.localise:
            self.loc = None
        elif new is not None and (self.loc is None or self.loc.grid != new.grid):
            new.init_pose(*self.odom.pose_mm())
            self.loc = new

    @property
    def nav(self) -> Localiser | Odometry:
        """The pose the robot drives by: the localiser's when it runs, else odometry."""
        return self.loc if self.loc is not None else self.odom

    def _event(self, kind: str, text: str, severity: int = SEV_INFO, seq: int = -1) -> None:
        self._events.append(VehicleEvent(kind=kind, text=text[:50], seq=seq, severity=severity))

    def _transition(self, dst: CtrlState, cause: str, severity: int = SEV_INFO) -> None:
        src = self.state
        if src == dst:
            return
        self.state = dst
        self.transitions.append(Transition(self._now, src, dst, cause))
        log.log(logging.WARNING if severity <= SEV_WARNING else logging.INFO,
                "t=%d us %s -> %s: %s", self._now, src.name, dst.name, cause)
        self._event("transition", f"{src.name}->{dst.name}: {cause}", severity)
        if src == CtrlState.DRIVING and dst != CtrlState.DRIVING:
            self._stop()
        if dst == CtrlState.DRIVING:
            self._driving_since_us = self._now

    def _interrupt_motion(self) -> None:
        """The kind abandons any motion in progress (a stop, a new goal, a new pose)."""
        if self.driver is not None:
            self.driver.interrupt()

    def _stop(self) -> None:
        self.watchdog.stop()
        self._interrupt_motion()
        self._stop_burst = STOP_BURST_TICKS

    def _enter_fault(self, cause: str) -> None:
        self.fault = cause
        self._transition(CtrlState.FAULT, cause, SEV_CRITICAL)
        self._event("fault", cause, SEV_CRITICAL)

    def _stale_inputs(self, inp: Inputs, now_us: int) -> list[str]:
        return self.freshness.stale(inp, now_us, self.cfg.sensor_timeout_ms * 1000)

    def _driver_status_stale(self, inp: Inputs, now_us: int) -> str:
        """"" while the motor driver's status is fresh, else why not: no status within the sensor
        timeout ("stale"), or frames whose rolling counter stopped advancing ("frozen": a stuck
        sender re-sending one frame)."""
        t = self.freshness.fresh_since(inp, "driver", inp.driver_us)
        if t is not None and now_us - t <= self.cfg.sensor_timeout_ms * 1000:
            return ""
        return "stale" if t == inp.driver_us else "frozen"

    def _goal_index_for(self, x_mm: int, y_mm: int, policy: Policy | None = None) -> tuple[int, str]:
        """The policy table's index of a goal (a cell policy's target; -1 and a reason if none)."""
        pol = policy or self.policy
        return (0, "") if pol is None else kinds.of_policy(pol).goal_index(pol, x_mm, y_mm)

    def _manual_driving(self) -> bool:
        """Armed in Manual, not in FAULT: the sticks drive (while fresh)."""
        return self.armed and self.mode == Mode.MANUAL and self.state == CtrlState.HOLD

    def _can_drive(self) -> tuple[bool, str]:
        if not self.armed:
            return False, "disarmed: arm first"
        if self.state == CtrlState.FAULT:
            return False, f"in FAULT ({self.fault}): disarm first"
        if self.policy is None:
            return False, "no policy loaded"
        if self._inputs.bumper:
            return False, "bumper pressed"
        if self.loc is not None and not self.loc.localised:
            sx, sy, sa = self.loc.std()
            return False, f"not localised (std {max(sx, sy):.0f} mm {sa:.0f} mrad)"
        return True, ""

    def _start_driving(self, goal: tuple[int, int], goal_index: int, cause: str) -> None:
        self.goal = goal
        self._goal_index = goal_index
        self._interrupt_motion()
        self.progress.restart()
        if self.state == CtrlState.DRIVING:
            log.info("t=%d us retarget: %s", self._now, cause)
            self._event("info", f"retarget: {cause}")
        else:
            self._transition(CtrlState.DRIVING, cause)
