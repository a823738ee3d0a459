"""The robot's control core: a pure state machine, one `step` per control tick.

`Controller.step(inputs, now_us) -> Outputs` reads the latest CAN inputs (each with the clock time it
arrived) and returns the motor command and heartbeat to send; no threads, sockets or clock reads (I/O
lives in `firmware_py.control.node`). It implements `firmware_py.vehicle.VehicleControl` for the
MAVLink node, whose calls come from another thread: every public method takes one lock, so a policy
swap lands between two ticks. States (CtrlState): BOOT -> STANDBY (disarmed) -> HOLD (armed) ->
DRIVING -> GOAL_REACHED -> next mission item or HOLD; FAULT from any armed state, left only by
disarming; every transition logged with its cause and queued as a VehicleEvent.

The controller is the state machine (states, modes, goal, mission, events) and holds its parts, each
fed its own inputs: `pose`, `safety`, `kind`, `monitor`, `out` and `activation` (what each takes and
gives back: docs/architecture.md, "The robot controller").
"""

from __future__ import annotations

import logging
import threading
from dataclasses import replace
from typing import Any

from firmware_py.control.activation import Activation
from firmware_py.control.collision import CollisionMonitor
from firmware_py.control.decision import KindPart
from firmware_py.control.estimate import PoseEstimate
from firmware_py.control.explore import Exploration, wander_wheels
from firmware_py.control.io import Inputs, Outputs, battery_fields, error_bits, sensor_view
from firmware_py.control.localiser import Localiser, LocaliserConfig
from firmware_py.control.manual import ManualSticks
from firmware_py.control.odometry import Odometry
from firmware_py.control.outputs import OutputStage
from firmware_py.control.progress import ProgressWatch, StallWatch
from firmware_py.control.route import Route
from firmware_py.control.safety import MotorWatchdog, SafetyChecks, clamp_speeds
from firmware_py.control.state import (
    SEV_CRITICAL,
    SEV_ERROR,
    SEV_INFO,
    SEV_NOTICE,
    SEV_WARNING,
    StateLog,
)
from firmware_py.kinds import DriveTick, KindDriver
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.mapdata import OccupancyGrid
from firmware_py.policy import Policy, config_mismatch
from firmware_py.vehicle import (
    CtrlState,
    FailsafeAction,
    Mode,
    PendingActivation,
    VehicleConfig,
    VehicleEvent,
    VehicleStatus,
)

log = logging.getLogger("qnav.controller")


class Controller:
    """The control state machine holding its parts; implements vehicle.VehicleControl."""

    def __init__(self, config: VehicleConfig | None = None, policy: Policy | None = None, *,
                 start_pose_mm: tuple[int, int, int] = (0, 0, 0), lockstep: bool = False,
                 localise: bool = True, localiser_config: LocaliserConfig | None = None,
                 profile: Any = None) -> None:
        self.cfg = config or VehicleConfig()
        self._lock = threading.RLock()
        self.lockstep = lockstep
        # qnav-robot --profile (firmware_py.profile.RobotProfile; None: the built-in robot): a policy
        # trained for another is refused (policy.config_mismatch)
        self.robot_profile: Any = profile
        # its body, wheels and sensors (firmware_py.layout), handed to each part
        self.layout = lay = profile.layout() if profile is not None else DEFAULT_LAYOUT
        self.pose = PoseEstimate(start_pose_mm, localise=localise, localiser_config=localiser_config, layout=lay)
        self.safety = SafetyChecks(bumper=lay.bumper)
        self.kind = KindPart(policy, lockstep=lockstep, layout=lay.sector_layout())
        self.monitor = CollisionMonitor(lay)
        self.out = OutputStage(self.cfg.motor_timeout_ms * 1000, lockstep)
        self.activation = Activation(self._lock, self.kind, self.pose, self.monitor, self)
        self.state = CtrlState.BOOT
        self.mode = Mode.HOLD
        self.armed = False
        self.failsafe = False
        self.fault = ""
        self.goal: tuple[int, int] | None = None
        self._goal_index = 0
        self.route = Route()  # the mission and its item in force
        self.progress = ProgressWatch()  # STATUSTEXT when the way is blocked
        self.stall = StallWatch()  # a drive getting nowhere for NAV_STALL_S: reported and held
        self.record = StateLog()  # transitions and events (control/state.py)
        self.transitions = self.record.transitions
        self._now = 0
        self._inputs = Inputs()
        self._driving_since_us = 0
        self._ticks = 0
        self._errors = 0
        self.tick_overruns = 0
        self.can_errors = 0
        self.exploration = Exploration()  # the wander for global localisation (armed, HOLD)
        self.manual = ManualSticks()  # Manual mode's sticks and deadman (control/manual.py)
        self._manual_was_driving = False
        self._arm_block = ""  # the last backend arming block reported (step says a new one once)
        self.pose.use(policy.map_grid if policy is not None else None, self._new_localiser(policy))

    # --- what the parts hold, as the rigs, tests and telemetry read it -----------------------
    policy = property(lambda self: self.kind.policy)
    driver: KindDriver | None = property(lambda self: self.kind.driver)  # type: ignore[assignment]
    last_known_good = property(lambda self: self.kind.last_known_good)
    background = property(lambda self: self.kind.background)
    target_mm = property(lambda self: self.kind.target_mm)
    robot_map = property(lambda self: self.kind.robot_map)
    odom: Odometry = property(lambda self: self.pose.odom)  # type: ignore[assignment]
    loc: Localiser | None = property(lambda self: self.pose.loc)  # type: ignore[assignment]
    nav: Localiser | Odometry = property(lambda self: self.pose.nav)  # type: ignore[assignment]
    encoder_jumps = property(lambda self: self.pose.encoder_jumps)
    collision_ticks = property(lambda self: self.monitor.ticks)
    watchdog: MotorWatchdog = property(lambda self: self.out.watchdog)  # type: ignore[assignment]
    _state_index = property(lambda self: self.kind.decided[0])
    _action = property(lambda self: self.kind.decided[1])

    # --- the state machine's primitives ------------------------------------------------------
    def _new_localiser(self, pol: Policy | None) -> Localiser | None:
        """A localiser for `pol`'s map (PoseEstimate.new_localiser; outside the lock)."""
        return self.pose.new_localiser(pol.map_grid if pol is not None else None)

    def busy(self) -> bool:
        return self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED)

    def route_items(self) -> list[tuple[int, int]]:
        return self.route.items

    def _note(self, text: str) -> None:
        log.info("t=%d us %s", self._now, text)
        self._event("info", text)

    def _event(self, kind: str, text: str, severity: int = SEV_INFO, seq: int = -1) -> None:
        self.record.event(kind, text, severity, seq)

    def _transition(self, dst: CtrlState, cause: str, severity: int = SEV_INFO) -> None:
        src = self.state
        if src == dst:
            return
        self.state = dst
        self.record.transition(self._now, src, dst, cause, severity)
        if src == CtrlState.DRIVING and dst != CtrlState.DRIVING:
            self._stop()
        if dst == CtrlState.DRIVING:
            self._driving_since_us = self._now

    def _stop(self) -> None:
        self.out.stop()
        self.kind.interrupt()

    def _enter_fault(self, cause: str) -> None:
        self.fault = cause
        self._transition(CtrlState.FAULT, cause, SEV_CRITICAL)
        self._event("fault", cause, SEV_CRITICAL)

    def _sectors(self, inp: Inputs) -> dict[str, list[int]]:
        """The readings as the policy's sectors (firmware_py.layout.Layout.to_sectors)."""
        if self.layout.identity():
            return {"ranges_mm": inp.ranges_mm, "range_status": inp.range_status}
        rs, ss = self.layout.to_sectors(inp.ranges_mm, inp.range_status)
        return {"ranges_mm": rs, "range_status": ss}

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
        loc = self.loc
        if loc is not None and not loc.localised:
            sx, sy, sa = loc.std()
            return False, f"not localised (std {max(sx, sy):.0f} mm {sa:.0f} mrad)"
        return True, ""

    def _start_driving(self, goal: tuple[int, int], goal_index: int, cause: str) -> None:
        self.goal = goal
        self._goal_index = goal_index
        self.kind.interrupt()
        self.progress.restart()
        if self.state == CtrlState.DRIVING:
            self._note(f"retarget: {cause}")
        else:
            self._transition(CtrlState.DRIVING, cause)

    # --- policy and map activation (control/activation.py) ------------------------------------
    def activate_policy(self, path: str) -> tuple[bool, str]:
        return self.activation.activate_policy(path)

    def begin_activation(self, path: str) -> tuple[bool, str] | PendingActivation:
        return self.activation.begin_activation(path)

    def activate_loaded(self, new: Policy, loc: Localiser | None = None,
                        claim: PendingActivation | None = None) -> tuple[bool, str]:
        return self.activation.activate_loaded(new, loc, claim)

    def begin_map_activation(self, path: str) -> tuple[bool, str] | PendingActivation:
        return self.activation.begin_map_activation(path)

    def set_robot_map(self, grid: OccupancyGrid, claim: PendingActivation | None = None) -> tuple[bool, str]:
        return self.activation.set_robot_map(grid, claim)

    def revert_policy(self) -> tuple[bool, str]:
        return self.activation.revert_policy()

    # --- VehicleControl ---------------------------------------------------------------
    def status(self) -> VehicleStatus:
        with self._lock:
            inp = self._inputs
            dist = bearing = 0
            nav, loc, odom, kind = self.nav, self.loc, self.odom, self.kind
            if self.goal is not None:
                dist, bearing = nav.goal_vector(*self.goal)
            x_mm, y_mm, heading_mrad = nav.pose_mm()
            std = loc.std() if loc is not None else (0.0, 0.0, 0.0)
            timeout_us = self.cfg.sensor_timeout_ms * 1000
            return VehicleStatus(
                time_us=self._now, state=CtrlState.MANUAL if self._manual_driving() else self.state,
                mode=self.mode, armed=self.armed,
                failsafe=self.failsafe, fault=self.fault,
                x_mm=x_mm, y_mm=y_mm, heading_mrad=heading_mrad,
                speed_mm_s=odom.speed_mm_s, yaw_rate_mrad_s=odom.yaw_rate_mrad_s,
                goal_mm=self.goal, distance_to_goal_mm=dist, bearing_to_goal_mrad=bearing,
                ranges_mm=list(inp.ranges_mm), range_status=list(inp.range_status),
                range_angles_mrad=self.layout.angles_mrad, range_max_mm=self.layout.max_range_mm,
                sensors_healthy=not self.safety.stale(inp, self._now, timeout_us),
                motors_healthy=not self.safety.driver_stale(inp, self._now, timeout_us) and inp.driver_errors == 0,
                bumper=inp.bumper, estop=self.safety.estop_latch.latched or inp.estop or inp.driver_estop,
                state_index=kind.decided[0], action=kind.decided[1], q_row=kind.decided[2],
                mission_seq=self.route.seq, mission_count=len(self.route),
                policy_id=self.policy.policy_id if self.policy else 0,
                policy_crc=self.policy.crc if self.policy else 0,
                map_mm=kind.map_mm(),
                ticks=self._ticks, tick_overruns=self.tick_overruns, can_errors=self.can_errors,
                odom_x_mm=odom.x_mm, odom_y_mm=odom.y_mm, odom_heading_mrad=odom.heading_mrad,
                localiser=("off" if loc is None else "global" if loc.global_mode else "tracking"),
                localised=loc is None or loc.localised,
                pose_std_mm=(round(std[0]), round(std[1])), pose_std_mrad=round(std[2]),
                **battery_fields(inp, self._now))

    def arm(self) -> tuple[bool, str]:
        with self._lock:
            if self.armed:
                return True, "already armed"
            if self.state == CtrlState.BOOT:
                return False, "still booting"
            why = self.safety.arm_refusal(self._inputs, self._now, self.cfg.sensor_timeout_ms * 1000)
            if why:
                return False, why
            self.armed = True
            self.fault = ""
            self._transition(CtrlState.HOLD, "armed")
            return True, ""

    def disarm(self) -> tuple[bool, str]:
        with self._lock:
            if not self.armed:
                return True, "already disarmed"
            self.armed = False
            self.safety.estop_latch.on_disarm()
            self._end_exploration("exploration stopped: disarmed")
            self._stop()
            self.goal = None
            self._transition(CtrlState.STANDBY, "disarmed")
            return True, ""

    def set_mode(self, mode: Mode) -> tuple[bool, str]:
        with self._lock:
            try:
                mode = Mode(mode)
            except ValueError:
                return False, f"unknown mode {mode}"
            self.mode = mode
            self.manual.clear()  # a stick from before the mode change never drives
            self._end_exploration(f"exploration stopped: mode {mode.name}")  # any mode command, Hold above all, ends the wander
            if mode in (Mode.HOLD, Mode.MANUAL) and self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                self.goal = None
                self._transition(CtrlState.HOLD, f"mode {mode.name}")
            elif mode == Mode.AUTO and self.armed and self.route.items and self.state != CtrlState.FAULT:
                return self.start_mission()  # the lock is reentrant
            return True, ""

    def manual_control(self, x: int, r: int, now_us: int) -> bool:
        """A MANUAL_CONTROL sample (control/manual.py); used only armed in Manual."""
        with self._lock:
            return self.manual.update(x, r, now_us)

    def set_goal(self, x_mm: int, y_mm: int) -> tuple[bool, str]:
        """A goal from the link (SET_POSITION_TARGET_*, a guided waypoint, DO_REPOSITION): taken only in
        Guided, as ArduPilot Rover does; it never switches another mode (Hold above all) to Guided."""
        return self._goal(x_mm, y_mm, switch=False)

    def go_to(self, x_mm: int, y_mm: int) -> tuple[bool, str]:
        """Mode Guided and the goal in one step, for whoever owns the robot locally (`qnav-robot
        --goal`, the rigs and benches): an operator's `mode guided` then a goal."""
        return self._goal(x_mm, y_mm, switch=True)

    def _goal(self, x_mm: int, y_mm: int, switch: bool) -> tuple[bool, str]:
        with self._lock:
            ok, why = self._can_drive()
            if not ok:
                return False, why
            if not switch and self.mode != Mode.GUIDED:
                return False, f"mode {self.mode.name.title()}, not Guided"  # one STATUSTEXT chunk
            gi, why = self.kind.goal_index(int(x_mm), int(y_mm))
            if gi < 0:
                return False, why
            self.mode = Mode.GUIDED
            self._start_driving((int(x_mm), int(y_mm)), gi, f"goal ({int(x_mm)},{int(y_mm)}) mm")
            return True, ""

    def set_mission(self, waypoints_mm: list[tuple[int, int]]) -> tuple[bool, str]:
        with self._lock:
            wps = [(int(x), int(y)) for x, y in waypoints_mm]
            why = Route.refusal(wps, self.kind.goal_index) if self.policy is not None else ""
            if why:
                return False, why
            self.route.replace(wps)
            if self.mode == Mode.AUTO and self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                self.goal = None
                self._transition(CtrlState.HOLD, "mission replaced")
            return True, ""

    def set_mission_current(self, seq: int) -> tuple[bool, str]:
        with self._lock:
            why = self.route.select(seq)
            if not why and self.mode == Mode.AUTO and self.state == CtrlState.DRIVING:
                x, y = self.route.current()
                self._start_driving((x, y), self.kind.goal_index(x, y)[0], f"mission item {seq}")
            return (False, why) if why else (True, "")

    def start_mission(self) -> tuple[bool, str]:
        with self._lock:
            ok, why = self._can_drive()
            if not ok or not self.route.items:
                return False, why or "no mission loaded"
            x, y = self.route.current()
            gi, why = self.kind.goal_index(x, y)
            if gi < 0:
                return False, f"item {self.route.seq}: {why}"
            self.mode = Mode.AUTO
            self._start_driving((x, y), gi, f"mission item {self.route.seq}")
            return True, ""

    def set_failsafe(self, active: bool) -> None:
        with self._lock:
            if active == self.failsafe:
                return
            self.failsafe = active
            if not active:
                self._event("info", "GCS failsafe cleared", SEV_NOTICE)
                return
            action = self.cfg.gcs_failsafe_action
            self._event("fault", "GCS Failsafe", SEV_CRITICAL)
            self._end_exploration("exploration stopped: GCS failsafe")  # whatever the action: the wander is never left running
            if not self.armed or action == FailsafeAction.NONE:
                return
            if action == FailsafeAction.DISARM:
                self.disarm()
            elif self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                self.mode = Mode.HOLD
                self.goal = None
                self._transition(CtrlState.HOLD, "GCS failsafe", SEV_CRITICAL)
            elif self.mode == Mode.MANUAL:  # the sticks come over the lost link: Hold, as ArduPilot
                self.mode = Mode.HOLD
                self.manual.clear()

    def check_config(self, cfg: VehicleConfig) -> tuple[bool, str]:
        """Refuse a config the active policy does not fit (policy.config_mismatch)."""
        with self._lock:
            if self.policy is None:
                return True, ""
            why = config_mismatch(self.policy, cfg.control_period_us, cfg.cell_size_mm, self.robot_map,
                                  self.robot_profile)
            return (False, why) if why else (True, "")

    def apply_config(self, cfg: VehicleConfig) -> None:
        """Take a new config (checked: check_config). One the active policy does not fit comes only from
        stored parameters at boot: the policy is unloaded (a warning says why), not run at a period it
        was not trained for; the robot stays in STANDBY until a matching one is activated."""
        with self._lock:
            self.cfg = replace(cfg)
            self.out.watchdog.timeout_us = max(1, cfg.motor_timeout_ms) * 1000
            ok, why = self.check_config(cfg)
            if not ok and self.policy is not None:
                log.warning("t=%d us policy 0x%08x unloaded: %s", self._now, self.policy.policy_id, why)
                self._event("refusal", why, SEV_WARNING)  # both values fit one STATUSTEXT
                if self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                    self.goal = None
                    self._stop()
                    self._transition(CtrlState.HOLD, "policy unloaded", SEV_WARNING)
                self.kind.install(None)

    def drain_events(self) -> list[VehicleEvent]:
        with self._lock:
            return self.record.drain()

    def localise_global(self, explore: bool = True) -> tuple[bool, str]:
        """Forget the pose (global localisation). With `explore` and armed in HOLD the robot wanders
        (control/explore.py; the one motion Hold allows) until converged, timed out, or the bumper, an
        e-stop, a fault, disarming, any mode command or a GCS failsafe; asking again does not extend
        it. Goals are refused until localised."""
        with self._lock:
            if self.loc is None:
                return False, "no map: the active policy carries none (qnav policy attach-map)"
            if self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                return False, "refused while driving: stop first"
            if explore and self.exploration.running:
                left_s = max(0, (self.exploration.until_us or 0) - self._now) / 1e6
                return True, f"already exploring, {left_s:.0f} s left"
            self.loc.init_global()
            self.exploration.start(self._now) if explore else self.exploration.stop()
            self._event("info", "global localisation started" + (", exploring" if explore else ""))
            return True, ""

    def _end_exploration(self, text: str, severity: int = SEV_WARNING) -> None:
        """Stop the wander now (the next tick commands zero), if it runs, saying why."""
        if self.exploration.running:
            self.exploration.stop()
            self._stop()
            self._event("info", text, severity)

    def _explore(self, inp: Inputs, now_us: int) -> None:
        """One tick of the wander that feeds global localisation (HOLD, armed)."""
        assert self.loc is not None
        done = self.exploration.end_reason(localised=not self.loc.global_mode, now_us=now_us,
                                           may_move=self.armed and self.state == CtrlState.HOLD and not inp.bumper)
        if done:
            self._end_exploration(done, SEV_INFO if done == "localised" else SEV_WARNING)
            return
        self.out.feed(now_us, *wander_wheels(**self._sectors(inp)))

    def note_loop_stats(self, overruns: int, can_errors: int) -> None:
        with self._lock:
            self.tick_overruns = overruns
            self.can_errors = can_errors

    # --- the tick -------------------------------------------------------------------------
    def step(self, inputs: Inputs, now_us: int, tick: int | None = None) -> Outputs:
        """One control tick at clock time `now_us`. `tick` is the SimTick
        counter being answered in lockstep (the motor command carries it)."""
        with self._lock:
            self._now = now_us
            self._inputs = inp = sensor_view(inputs, self.layout)
            self._ticks += 1
            if self.state == CtrlState.BOOT:
                what = f"policy 0x{self.policy.policy_id:08x}" if self.policy else "no policy"
                self._transition(CtrlState.STANDBY, f"boot complete, {what}")
            self.safety.freshness.note_counters(inp)
            enc_jump = self.pose.encoders(inp)
            if enc_jump and self.armed and self.state != CtrlState.FAULT:
                self._enter_fault(enc_jump)
            said = self.pose.localise_tick(inp, self.kind.localiser_margin_mm)
            if said:
                self._event("info", said, SEV_INFO if said == "localised" else SEV_WARNING)
            if bool(inp.arm_block) != bool(self._arm_block) and inp.arm_block:
                self._event("warning", inp.arm_block, SEV_WARNING)  # a backend's arming block (DroneCAN
            self._arm_block = inp.arm_block  # node-id collision), said once when it begins (its text ages)
            errors = self._safety(inp, now_us)
            if self.state == CtrlState.GOAL_REACHED:
                self._after_goal()
            if self.state == CtrlState.DRIVING:
                self._drive(inp, now_us)
            elif self.exploration.running:
                self._explore(inp, now_us)
            manual = self._manual_driving()
            if manual:
                self.out.feed(now_us, *self.manual.wheels(now_us, self.cfg.max_wheel_speed_mm_s, inp.bumper))
            elif self._manual_was_driving:  # Hold, disarm, failsafe, FAULT: the wheels stop this tick
                self._stop()
            self._manual_was_driving = manual
            if self.state != CtrlState.DRIVING:
                # no decision in force; while DRIVING the last one holds until the next (a
                # cell policy decides once per cell move), so telemetry always shows it
                self.kind.decided = (-1, -1, ())
            return self._outputs(now_us, tick, errors)

    def _safety(self, inp: Inputs, now_us: int) -> int:
        v = self.safety.check(inp, now_us, self.cfg.sensor_timeout_ms * 1000, armed=self.armed,
                              driving_since_us=self._driving_since_us if self.state == CtrlState.DRIVING else None,
                              grace_us=2 * self.cfg.control_period_us)
        if self.armed:
            if v.estop_tripped:
                self._enter_fault("e-stop engaged")
            if self.state != CtrlState.FAULT and v.fault:
                self._enter_fault(v.fault)
            if inp.bumper and self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                self.goal = None
                self.mode = Mode.HOLD
                self._transition(CtrlState.HOLD, "bumper pressed", SEV_WARNING)
        self._errors = error_bits(inp, stale=bool(v.stale), driver_silent=bool(v.driver_stale),
                                  no_policy=self.policy is None, failsafe=self.failsafe,
                                  estop_latched=self.safety.estop_latch.latched,
                                  localisation_fault=self.fault.startswith("localisation"))
        return self._errors

    def _after_goal(self) -> None:
        nxt = self.route.advance() if self.mode == Mode.AUTO else None
        if nxt is not None:
            gi, why = self.kind.goal_index(*nxt)
            if gi >= 0:
                self.goal, self._goal_index = nxt, gi
                self.kind.interrupt()
                self._transition(CtrlState.DRIVING, f"next mission item {self.route.seq}")
                return
            self._event("refusal", f"item {self.route.seq}: {why}", SEV_WARNING)
        cause = "mission complete" if self.mode == Mode.AUTO else "goal reached"
        if self.mode == Mode.AUTO:
            self.mode = Mode.HOLD
        self.goal = None
        self._transition(CtrlState.HOLD, cause)

    def _end_drive(self, kind: str, text: str, severity: int, cause: str) -> None:
        """The drive ends without its goal: say why (STATUSTEXT) and hold (mode Hold)."""
        self._event(kind, text, severity, seq=self.route.seq if self.mode == Mode.AUTO else -1)
        self.mode = Mode.HOLD
        self.goal = None
        self._transition(CtrlState.HOLD, cause, SEV_WARNING if kind == "stall" else SEV_INFO)

    def _drive(self, inp: Inputs, now_us: int) -> None:
        assert self.goal is not None and self.policy is not None and self.driver is not None
        nav = self.nav
        dist, bearing = nav.goal_vector(*self.goal)
        auto = self.mode == Mode.AUTO
        if dist <= self.cfg.goal_tolerance_mm:
            self._transition(CtrlState.GOAL_REACHED, f"goal reached, {dist} mm off")
            if auto:
                self._event("mission_item_reached", f"reached item {self.route.seq}", seq=self.route.seq)
            return
        stalled = self.progress.update(now_us, self.goal, dist)
        if stalled:
            self._event("info", (f"item {self.route.seq}: " if auto else "") + stalled, SEV_WARNING)
        x_mm, y_mm, _ = nav.pose_mm()
        why = self.stall.update(now_us, (self.goal, self._driving_since_us), dist, x_mm, y_mm,
                                self.cfg.nav_stall_s * 1_000_000)
        if why:
            # nowhere for NAV_STALL_S (control/progress.StallWatch): hold, as ArduPilot's rover holds on a
            # failsafe and nav2's progress checker aborts the goal; the item stays current (Auto retries)
            item = f"item {self.route.seq}: " if auto else ""
            self._end_drive("stall", f"{item}stalled: {why}, {dist} mm to go", SEV_WARNING, f"stalled: {why}")
            return
        # the kind decides (firmware_py.kinds); the controller only scales, clamps and feeds the watchdog
        d = self.kind.step(DriveTick(
            now_us=now_us, goal=self.goal, goal_index=self._goal_index, drive_key=(self.goal, self._driving_since_us),
            pose_mm=nav.pose_mm(), goal_bearing_mrad=bearing, **self._sectors(inp), goal_vector=nav.goal_vector,
            blocked_us=self.monitor.held_us(now_us)))
        if d.no_route:
            # the kind's planner found no way (its recoveries ran out): report it (error) and end the
            # mission or goal in HOLD, as ArduPilot's rover holds when its path planner fails
            item = f"mission item {self.route.seq}: " if auto else "goal: "
            self._end_drive("no_route", item + d.no_route, SEV_ERROR,
                            d.no_route if d.no_route.startswith("no route") else "no route: " + d.no_route)
            return
        if d.wheels is None:
            if d.fault:
                self._enter_fault(d.fault)
            return
        left, right = d.wheels
        pct = self.cfg.speed_scale_pct
        self.out.feed(now_us, *clamp_speeds(left * pct // 100, right * pct // 100, self.cfg.max_wheel_speed_mm_s))

    def _outputs(self, now_us: int, tick: int | None, errors: int) -> Outputs:
        cfg, inp = self.cfg, self._inputs
        left, right = self.out.setpoint(now_us, cfg.max_wheel_speed_mm_s)
        if left or right:  # the collision monitor has the last word on any motion (control/collision.py)
            left, right = self.monitor.limit_command(
                now_us, left, right, inp.ranges_mm, inp.range_status, self.nav.pose_mm(), self.kind.remembered(),
                self.kind.monitor_map(), cfg.collision_stop_mm, cfg.collision_slow_mm, cfg.collision_slow_pct)
        else:
            self.monitor.stop_since_us = None
        if self.state == CtrlState.DRIVING:  # what the stall watch tells the reason by
            shut = self.monitor.shut(left, right, inp.ranges_mm, inp.range_status, cfg.collision_slow_mm)
            self.stall.note(bool(left or right), shut, None if inp.enc_us is None else (inp.enc_left, inp.enc_right))
        moving = self.state == CtrlState.DRIVING or self.exploration.running or self._manual_driving()
        return self.out.frames(now_us, tick, left, right, moving=moving, state=int(self.state), mode=int(self.mode),
                               armed=self.armed, policy_loaded=self.policy is not None,
                               goal_active=self.goal is not None, errors=errors,
                               drive_enabled=moving and self.state != CtrlState.FAULT)
