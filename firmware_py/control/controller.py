"""The robot's control core: a pure state machine, one `step` per control tick.

`Controller.step(inputs, now_us) -> Outputs` reads the latest CAN inputs
(each with the clock time it arrived), runs safety, odometry and the policy,
and returns the motor command and heartbeat to send. No threads, sockets or
clock reads here: time comes in as an argument, I/O lives in
`firmware_py.control.node`. The controller also implements
`firmware_py.vehicle.VehicleControl` for the MAVLink node; those calls may
come from another thread, so every public method takes one lock and a policy
swap lands between two ticks (policy and map activation: its base, control/activation.py).

States (CtrlState): BOOT -> STANDBY (disarmed) -> HOLD (armed, no goal) ->
DRIVING -> GOAL_REACHED -> next mission item or HOLD; FAULT from any armed
state, left only by disarming. Every transition is logged with its cause and
queued as a VehicleEvent. See docs/architecture.md.

Decision: the active policy's kind (firmware_py.kinds: cell, sector, sector-memory) turns each
DRIVING tick into a wheel command; the controller only scales and clamps it and feeds the watchdog.
It knows no kind: the registry builds the kind's driver when a policy is activated.
"""

from __future__ import annotations

import logging
from dataclasses import replace

from firmware_py import robot_spec
from firmware_py.can_protocol import MOTOR_WATCHDOG_STOP
from firmware_py.control import collision
from firmware_py.control.activation import Activation
from firmware_py.control.collision import mapped_readings
from firmware_py.control.explore import wander_wheels
from firmware_py.control.io import (
    Heartbeat,
    Inputs,
    MotorCommand,
    Outputs,
    error_bits,
)
from firmware_py.control.plausibility import encoder_jump
from firmware_py.control.route import Route
from firmware_py.control.safety import clamp_speeds
from firmware_py.control.state import (
    SEV_CRITICAL,
    SEV_ERROR,
    SEV_INFO,
    SEV_NOTICE,
    SEV_WARNING,
)
from firmware_py.kinds import DriveTick
from firmware_py.mapdata import OccupancyGrid
from firmware_py.policy import config_mismatch
from firmware_py.vehicle import (
    CtrlState,
    FailsafeAction,
    Mode,
    VehicleConfig,
    VehicleEvent,
    VehicleStatus,
)

log = logging.getLogger("qnav.controller")

BATTERY_TIMEOUT_US = 5_000_000  # the power board reports at 2 Hz


class Controller(Activation):
    """The control state machine; implements vehicle.VehicleControl."""

    # --- VehicleControl ---------------------------------------------------------------
    def status(self) -> VehicleStatus:
        with self._lock:
            inp = self._inputs
            dist = bearing = 0
            if self.goal is not None:
                dist, bearing = self.nav.goal_vector(*self.goal)
            x_mm, y_mm, heading_mrad = self.nav.pose_mm()
            std = self.loc.std() if self.loc is not None else (0.0, 0.0, 0.0)
            return VehicleStatus(
                time_us=self._now, state=CtrlState.MANUAL if self._manual_driving() else self.state,
                mode=self.mode, armed=self.armed,
                failsafe=self.failsafe, fault=self.fault,
                x_mm=x_mm, y_mm=y_mm, heading_mrad=heading_mrad,
                speed_mm_s=self.odom.speed_mm_s, yaw_rate_mrad_s=self.odom.yaw_rate_mrad_s,
                goal_mm=self.goal, distance_to_goal_mm=dist, bearing_to_goal_mrad=bearing,
                ranges_mm=list(inp.ranges_mm), range_status=list(inp.range_status),
                sensors_healthy=not self._stale_inputs(inp, self._now),
                motors_healthy=not self._driver_status_stale(inp, self._now) and inp.driver_errors == 0,
                bumper=inp.bumper, estop=self.estop_latch.latched or inp.estop or inp.driver_estop,
                state_index=self._state_index, action=self._action, q_row=self._q_row,
                mission_seq=self.route.seq, mission_count=len(self.route),
                policy_id=self.policy.policy_id if self.policy else 0,
                policy_crc=self.policy.crc if self.policy else 0,
                map_mm=self._map_mm(),
                ticks=self._ticks, tick_overruns=self.tick_overruns, can_errors=self.can_errors,
                odom_x_mm=self.odom.x_mm, odom_y_mm=self.odom.y_mm, odom_heading_mrad=self.odom.heading_mrad,
                localiser=("off" if self.loc is None else "global" if self.loc.global_mode else "tracking"),
                localised=self.loc is None or self.loc.localised,
                pose_std_mm=(round(std[0]), round(std[1])), pose_std_mrad=round(std[2]),
                **self._battery(inp))

    def _battery(self, inp: Inputs) -> dict[str, int]:
        """The last BatteryStatus, or unknown when none came within BATTERY_TIMEOUT_US (a board that fell
        silent must not show a full battery forever)."""
        if inp.battery_us is None or self._now - inp.battery_us > BATTERY_TIMEOUT_US:
            return {}
        return {"battery_mv": inp.battery_mv, "battery_ma": inp.battery_ma, "battery_pct": inp.battery_pct}

    def _map_mm(self) -> tuple[int, int] | None:
        """The robot's map extent in world mm (x east, y north, from 0): the
        active policy's recorded map geometry; None without one."""
        geo = self.policy.map_geometry if self.policy is not None else None
        if geo is None or geo.cell_mm <= 0 or geo.width <= 0 or geo.height <= 0:
            return None
        return geo.width * geo.cell_mm, geo.height * geo.cell_mm

    def arm(self) -> tuple[bool, str]:
        with self._lock:
            if self.armed:
                return True, "already armed"
            if self.state == CtrlState.BOOT:
                return False, "still booting"
            inp = self._inputs
            ok, why = self.estop_latch.may_arm(inp.estop or inp.driver_estop)
            if not ok:
                return False, why
            stale = self._stale_inputs(inp, self._now)
            if stale:
                return False, f"sensor data stale: {','.join(stale)}"
            if self._driver_status_stale(inp, self._now):
                return False, "motor driver silent"
            if inp.driver_errors:
                return False, inp.driver_detail or f"motor driver errors 0x{inp.driver_errors:02x}"
            if inp.arm_block:
                return False, inp.arm_block
            self.armed = True
            self.fault = ""
            self._transition(CtrlState.HOLD, "armed")
            return True, ""

    def disarm(self) -> tuple[bool, str]:
        with self._lock:
            if not self.armed:
                return True, "already disarmed"
            self.armed = False
            self.estop_latch.on_disarm()
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
                return self._start_mission_locked()
            return True, ""

    def manual_control(self, x: int, r: int, now_us: int) -> bool:
        """A MANUAL_CONTROL sample (control/manual.py); used only armed in Manual."""
        with self._lock:
            return self.manual.update(x, r, now_us)

    def set_goal(self, x_mm: int, y_mm: int) -> tuple[bool, str]:
        """A goal from the link (SET_POSITION_TARGET_*, a guided-mode waypoint,
        DO_REPOSITION): taken only in Guided, as ArduPilot Rover takes position
        targets; it never switches another mode (Hold above all) to Guided.
        DO_REPOSITION with its CHANGE_MODE flag sets Guided itself first."""
        return self._goal(x_mm, y_mm, switch=False)

    def go_to(self, x_mm: int, y_mm: int) -> tuple[bool, str]:
        """Mode Guided and the goal in one step, for whoever owns the robot
        locally (`qnav-robot --goal`, the rigs and benches): what an operator
        does with `mode guided` then a goal."""
        return self._goal(x_mm, y_mm, switch=True)

    def _goal(self, x_mm: int, y_mm: int, switch: bool) -> tuple[bool, str]:
        with self._lock:
            ok, why = self._can_drive()
            if not ok:
                return False, why
            if not switch and self.mode != Mode.GUIDED:
                return False, f"mode {self.mode.name.title()}, not Guided"  # one STATUSTEXT chunk
            gi, why = self._goal_index_for(int(x_mm), int(y_mm))
            if gi < 0:
                return False, why
            self.mode = Mode.GUIDED
            self._start_driving((int(x_mm), int(y_mm)), gi, f"goal ({int(x_mm)},{int(y_mm)}) mm")
            return True, ""

    def set_mission(self, waypoints_mm: list[tuple[int, int]]) -> tuple[bool, str]:
        with self._lock:
            wps = [(int(x), int(y)) for x, y in waypoints_mm]
            why = Route.refusal(wps, self._goal_index_for) if self.policy is not None else ""
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
                self._start_driving((x, y), self._goal_index_for(x, y)[0], f"mission item {seq}")
            return (False, why) if why else (True, "")

    def _start_mission_locked(self) -> tuple[bool, str]:
        ok, why = self._can_drive()
        if not ok or not self.route.items:
            return False, why or "no mission loaded"
        x, y = self.route.current()
        gi, why = self._goal_index_for(x, y)
        if gi < 0:
            return False, f"item {self.route.seq}: {why}"
        self.mode = Mode.AUTO
        self._start_driving((x, y), gi, f"mission item {self.route.seq}")
        return True, ""

    def start_mission(self) -> tuple[bool, str]:
        with self._lock:
            return self._start_mission_locked()

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
        """Take a new config. Parameter changes were checked (check_config); a
        config that does not fit the active policy arrives only from stored
        parameters at boot or reboot, and then the policy is unloaded (with
        the reason as a warning) rather than run at a period it was not
        trained for: the robot stays in STANDBY until a matching one is
        activated."""
        with self._lock:
            self.cfg = replace(cfg)
            self.watchdog.timeout_us = max(1, cfg.motor_timeout_ms) * 1000
            ok, why = self.check_config(cfg)
            if not ok and self.policy is not None:
                log.warning("t=%d us policy 0x%08x unloaded: %s", self._now, self.policy.policy_id, why)
                self._event("refusal", why, SEV_WARNING)  # both values fit one STATUSTEXT
                if self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                    self.goal = None
                    self._stop()
                    self._transition(CtrlState.HOLD, "policy unloaded", SEV_WARNING)
                self.policy = self.driver = None

    def drain_events(self) -> list[VehicleEvent]:
        with self._lock:
            out = list(self._events)
            self._events.clear()
            return out

    def localise_global(self, explore: bool = True) -> tuple[bool, str]:
        """Forget the pose: particles uniform over the map (global localisation). With `explore`
        and armed in HOLD the robot wanders (control/explore.py), the one motion Hold allows and
        only on this request, until the localiser has converged, its time is up, or the bumper,
        an e-stop, a fault, disarming, any mode command (Hold included) or a GCS failsafe ends it
        at once. Asking again while it wanders does not extend it. Goals are refused until the
        pose is localised."""
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
        self.watchdog.feed(now_us, *wander_wheels(inp.ranges_mm, inp.range_status))

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
            self._inputs = inputs
            self._ticks += 1
            inp = inputs
            if self.state == CtrlState.BOOT:
                what = f"policy 0x{self.policy.policy_id:08x}" if self.policy else "no policy"
                self._transition(CtrlState.STANDBY, f"boot complete, {what}")
            self.freshness.note_counters(inp)
            enc_jump = ""
            if inp.enc_us is not None and inp.enc_us != self._last_enc_us:
                enc_jump = self._encoder_jump(inp)
                if enc_jump:
                    self.encoder_jumps += 1
                    self.odom.rebase(inp.enc_left, inp.enc_right, inp.enc_us)  # the pose stays put
                else:
                    self.odom.update(inp.enc_left, inp.enc_right, inp.enc_us)
                self._last_enc_us = inp.enc_us
            if enc_jump and self.armed and self.state != CtrlState.FAULT:
                self._enter_fault(enc_jump)
            if self.loc is not None:
                was = self.loc.localised
                self.loc.tick(self.odom.pose_mm(), inp.ranges_mm, self._statuses_for_localiser(inp))
                if self.loc.localised != was:
                    self._event("info", "localised" if self.loc.localised else "localisation lost",
                                SEV_INFO if self.loc.localised else SEV_WARNING)
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
                left, right = self.manual.wheels(now_us, self.cfg.max_wheel_speed_mm_s, inp.bumper)
                self.watchdog.feed(now_us, left, right)
            elif self._manual_was_driving:  # Hold, disarm, failsafe, FAULT: the wheels stop this tick
                self._stop()
            self._manual_was_driving = manual
            if self.state != CtrlState.DRIVING:
                # no decision in force; while DRIVING the last one holds until the next (a
                # cell policy decides once per cell move), so telemetry always shows it
                self._state_index = self._action = -1
                self._q_row = ()
            return self._outputs(now_us, tick, errors)

    def _encoder_jump(self, inp: Inputs) -> str:
        """Why the new encoder sample is implausible ("" if it is not)."""
        d = self.odom.deltas(inp.enc_left, inp.enc_right)
        if d is None or self._last_enc_us is None or inp.enc_us is None:
            return ""
        return encoder_jump(d, max(0, inp.enc_us - self._last_enc_us))

    def _safety(self, inp: Inputs, now_us: int) -> int:
        estop = inp.estop or inp.driver_estop
        stale = self._stale_inputs(inp, now_us)
        driver_stale = self._driver_status_stale(inp, now_us)
        if self.armed:
            if estop and self.estop_latch.trip():
                self._enter_fault("e-stop engaged")
            if self.state != CtrlState.FAULT:
                detail = f": {inp.driver_detail}" if inp.driver_detail else ""
                if stale:
                    self._enter_fault(f"sensor data stale: {','.join(stale)}" + (detail if "encoders" in stale else ""))
                elif driver_stale:
                    self._enter_fault(f"motor driver status {driver_stale}{detail}")
                elif inp.driver_errors:
                    self._enter_fault(inp.driver_detail or f"motor driver fault 0x{inp.driver_errors:02x}")
                elif self._driver_watchdog_tripped(inp):
                    self._enter_fault("motor driver watchdog tripped while driving")
            if inp.bumper and self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                self.goal = None
                self.mode = Mode.HOLD
                self._transition(CtrlState.HOLD, "bumper pressed", SEV_WARNING)
        self._errors = error_bits(inp, stale=bool(stale), driver_silent=bool(driver_stale), no_policy=self.policy is None,
                                  failsafe=self.failsafe, estop_latched=self.estop_latch.latched,
                                  localisation_fault=self.fault.startswith("localisation"))
        return self._errors

    def _driver_watchdog_tripped(self, inp: Inputs) -> bool:
        """The driver stopped the wheels for want of commands although we are
        DRIVING (commands lost on the way). Its status may still show the
        HOLD-time watchdog stop for a tick or two after DRIVING starts."""
        grace_us = 2 * self.cfg.control_period_us
        return (self.state == CtrlState.DRIVING and inp.driver_state == MOTOR_WATCHDOG_STOP
                and inp.driver_us is not None and inp.driver_us - self._driving_since_us > grace_us)

    def _after_goal(self) -> None:
        nxt = self.route.advance() if self.mode == Mode.AUTO else None
        if nxt is not None:
            gi, why = self._goal_index_for(*nxt)
            if gi >= 0:
                self.goal, self._goal_index = nxt, gi
                self._interrupt_motion()
                self._transition(CtrlState.DRIVING, f"next mission item {self.route.seq}")
                return
            self._event("refusal", f"item {self.route.seq}: {why}", SEV_WARNING)
        cause = "mission complete" if self.mode == Mode.AUTO else "goal reached"
        if self.mode == Mode.AUTO:
            self.mode = Mode.HOLD
        self.goal = None
        self._transition(CtrlState.HOLD, cause)

    def _no_route(self, why: str) -> None:
        """The kind's planner found no way to the goal (its recoveries ran out): report it (STATUSTEXT,
        error) and end the mission or goal in HOLD (as ArduPilot's rover holds when its path planner
        fails), the wheels stopped. A new goal or mission start tries again."""
        item = f"mission item {self.route.seq}: " if self.mode == Mode.AUTO else "goal: "
        self._event("no_route", item + why, SEV_ERROR, seq=self.route.seq if self.mode == Mode.AUTO else -1)
        self.mode = Mode.HOLD
        self.goal = None
        self._transition(CtrlState.HOLD, why if why.startswith("no route") else "no route: " + why)

    def _stalled(self, why: str, dist: int) -> None:
        """The drive got nowhere for NAV_STALL_S (control/progress.StallWatch): say why (STATUSTEXT,
        warning) and hold, as ArduPilot's rover holds on a failsafe and nav2's progress checker
        aborts the goal; the mission item stays current, so mode Auto tries it again."""
        item = f"item {self.route.seq}: " if self.mode == Mode.AUTO else ""
        self._event("stall", f"{item}stalled: {why}, {dist} mm to go", SEV_WARNING,
                    seq=self.route.seq if self.mode == Mode.AUTO else -1)
        self.mode = Mode.HOLD
        self.goal = None
        self._transition(CtrlState.HOLD, f"stalled: {why}", SEV_WARNING)

    def _drive(self, inp: Inputs, now_us: int) -> None:
        assert self.goal is not None and self.policy is not None and self.driver is not None
        dist, bearing = self.nav.goal_vector(*self.goal)
        if dist <= self.cfg.goal_tolerance_mm:
            self._transition(CtrlState.GOAL_REACHED, f"goal reached, {dist} mm off")
            if self.mode == Mode.AUTO:
                self._event("mission_item_reached", f"reached item {self.route.seq}", seq=self.route.seq)
            return
        stalled = self.progress.update(now_us, self.goal, dist)
        if stalled:
            item = f"item {self.route.seq}: " if self.mode == Mode.AUTO else ""
            self._event("info", item + stalled, SEV_WARNING)
        x_mm, y_mm, _ = self.nav.pose_mm()
        why = self.stall.update(now_us, (self.goal, self._driving_since_us), dist, x_mm, y_mm,
                                self.cfg.nav_stall_s * 1_000_000)
        if why:
            self._stalled(why, dist)
            return
        # the kind decides (firmware_py.kinds); the controller only scales, clamps and feeds the watchdog
        d = self.driver.step(DriveTick(
            now_us=now_us, goal=self.goal, goal_index=self._goal_index, drive_key=(self.goal, self._driving_since_us),
            pose_mm=self.nav.pose_mm(), goal_bearing_mrad=bearing, ranges_mm=inp.ranges_mm,
            range_status=inp.range_status, goal_vector=self.nav.goal_vector,
            blocked_us=0 if self._cm_stop_since_us is None else now_us - self._cm_stop_since_us))
        if d.decided is not None:
            self._state_index, self._action, self._q_row = d.decided
        self.target_mm = d.target_mm
        if d.no_route:
            self._no_route(d.no_route)
            return
        if d.wheels is None:
            if d.fault:
                self._enter_fault(d.fault)
            return
        left, right = d.wheels
        pct = self.cfg.speed_scale_pct
        left, right = clamp_speeds(left * pct // 100, right * pct // 100, self.cfg.max_wheel_speed_mm_s)
        self.watchdog.feed(now_us, left, right)

    def _statuses_for_localiser(self, inp: Inputs) -> list[int]:
        """The range statuses the localiser weighs: the kind may withhold readings it knows the map
        does not explain at the tracked pose (the sector kind's unmapped obstacles)."""
        status = list(inp.range_status)
        loc = self.loc
        if self.driver is None or loc is None or not loc.localised:
            return status
        return self.driver.localiser_statuses(loc.pose_mm(), inp.ranges_mm, status)

    def _monitor_map(self) -> OccupancyGrid | None:
        """The map the collision monitor knows walls and corners by: the robot's, else the policy's."""
        return self.robot_map if self.robot_map is not None else (
            self.policy.map_grid if self.policy is not None else None)

    def _map_corners_near(self, pose: tuple[int, int, int]) -> list[tuple[int, int]]:
        """The robot's map's block corners within reach of the collision monitor (none without a map)."""
        grid = self._monitor_map()
        if grid is None:
            return []
        corners: collision.MapCorners | None = self._corners
        if corners is None or corners.grid is not grid:
            self._corners = corners = collision.MapCorners(grid)
        return corners.near(pose[0], pose[1], self.cfg.collision_slow_mm + 2 * robot_spec.ROBOT_RADIUS_MM)

    def _outputs(self, now_us: int, tick: int | None, errors: int) -> Outputs:
        left, right = self.watchdog.output(now_us)
        left, right = clamp_speeds(left, right, self.cfg.max_wheel_speed_mm_s)
        if left or right:  # the collision monitor has the last word on any motion (control/collision.py)
            cfg, inp = self.cfg, self._inputs
            pose = self.nav.pose_mm()
            seen = self.driver.remembered_obstacles() if self.driver is not None else []
            seen = seen + self._map_corners_near(pose)
            near = collision.robot_frame(seen, pose) if seen else []
            grid = self._monitor_map()
            mapped = mapped_readings(grid, pose, inp.ranges_mm, inp.range_status) if grid is not None else []
            left, right, limited = collision.limit(left, right, inp.ranges_mm, inp.range_status, cfg.collision_stop_mm,
                                                   cfg.collision_slow_mm, cfg.collision_slow_pct, near, mapped)
            if limited:
                self.collision_ticks[limited] += 1
            if limited == "stop":
                if self._cm_stop_since_us is None:
                    self._cm_stop_since_us = now_us
            else:
                self._cm_stop_since_us = None
        else:
            self._cm_stop_since_us = None
        if self.state == CtrlState.DRIVING:  # what the stall watch tells the reason by
            inp = self._inputs
            shut = self._cm_stop_since_us is not None or (not (left or right) and collision.travel_gap_mm(
                inp.ranges_mm, inp.range_status, False) < self.cfg.collision_slow_mm)
            self.stall.note(bool(left or right), shut,
                            None if inp.enc_us is None else (inp.enc_left, inp.enc_right))
        if tick is not None:
            counter = tick & 0xFFFFFF
        else:
            self._cmd_counter = (self._cmd_counter + 1) & 0xFFFFFF
            counter = self._cmd_counter
        moving = self.state == CtrlState.DRIVING or self.exploration.running or self._manual_driving()
        live = moving and not self.watchdog.expired(now_us)
        if live or self.lockstep or tick is not None:
            motor = MotorCommand(left, right, counter)
        elif self._stop_burst > 0:
            self._stop_burst -= 1
            motor = MotorCommand(0, 0, counter)
        else:
            motor = None
        self._hb_counter = (self._hb_counter + 1) & 0xFF
        hb = Heartbeat(state=int(self.state), mode=int(self.mode), armed=self.armed,
                       policy_loaded=self.policy is not None, goal_active=self.goal is not None,
                       errors=errors, counter=self._hb_counter)
        return Outputs(motor=motor, heartbeat=hb, drive_enabled=moving and self.state != CtrlState.FAULT)
