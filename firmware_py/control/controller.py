"""The robot's control core: a pure state machine, one `step` per control tick.

`Controller.step(inputs, now_us) -> Outputs` reads the latest CAN inputs
(each with the clock time it arrived), runs safety, odometry and the policy,
and returns the motor command and heartbeat to send. No threads, sockets or
clock reads here: time comes in as an argument, I/O lives in
`firmware_py.control.node`. The controller also implements
`firmware_py.vehicle.VehicleControl` for the MAVLink node; those calls may
come from another thread, so every public method takes one lock and a policy
swap lands between two ticks.

States (CtrlState): BOOT -> STANDBY (disarmed) -> HOLD (armed, no goal) ->
DRIVING -> GOAL_REACHED -> next mission item or HOLD; FAULT from any armed
state, left only by disarming. Every transition is logged with its cause and
queued as a VehicleEvent. See docs/architecture.md.

Decision: `sector` policies map (goal bearing, ranges) through the reference
encoder to a row of the int table; the greedy action's wheel speeds come from
robot_spec.ACTION_WHEEL_SPEEDS_MM_S and are held for one tick. `cell` policies run
as motion primitives: localise the cell from odometry, take the greedy grid
action, turn in place to its grid heading, drive to the next cell's centre,
re-localise and repeat. `sector-memory` policies (firmware_py.gridbug) run on
the same executor: at a cell centre facing a grid direction, the Bug memory
and the four axis sensors give the row, the greedy relative move the next
cell (`_grid_decision`).
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import dataclass, field, replace

from firmware_py import robot_spec
from firmware_py.can_protocol import ENCODER_BITS, MOTOR_WATCHDOG_STOP
from firmware_py.control.localiser import Localiser, LocaliserConfig
from firmware_py.control.odometry import Odometry, wrap_mrad
from firmware_py.control.progress import ProgressWatch
from firmware_py.control.safety import EStopLatch, MotorWatchdog, clamp_speeds
from firmware_py.encoders import CellEncoder, SectorEncoder
from firmware_py.gridbug import (
    DIR_HEADING_MRAD,
    DIR_VECTORS,
    GridBugEncoder,
    GridBugMemory,
    grid_dir_of,
)
from firmware_py.localplan import LocalPlanner, MotionGuard, ObstacleMemory, unmapped_readings
from firmware_py.policy import Policy, PolicyError, config_mismatch, load_policy
from firmware_py.vehicle import (
    CtrlState,
    FailsafeAction,
    Mode,
    VehicleConfig,
    VehicleEvent,
    VehicleStatus,
)

log = logging.getLogger("qnav.controller")

# Ctrl_Errors bit field of the controller heartbeat (docs/can-protocol.md).
ERR_SENSOR_STALE = 1 << 0
ERR_DRIVER_FAULT = 1 << 1
ERR_ESTOP = 1 << 2
ERR_BUMPER = 1 << 3
ERR_NO_POLICY = 1 << 4
ERR_DRIVER_SILENT = 1 << 5
ERR_FAILSAFE = 1 << 6
ERR_LOCALISATION = 1 << 7

SEV_CRITICAL = 2
SEV_ERROR = 3
SEV_WARNING = 4
SEV_NOTICE = 5
SEV_INFO = 6

# Cell motion primitive tuning (integers: mrad, mm, mm/s).
TURN_TOLERANCE_MRAD = 35  # heading error at which a turn counts as done
ARRIVE_TOLERANCE_MM = 30  # distance to a cell centre at which a step is done
RETURN_TO_TURN_MRAD = 600  # bearing error that aborts a straight drive back to turning
# sector-memory (cell-stepped) decisions wait for a valid reading of the four axis sensors this many ticks
# (the realistic plant drops 2 % of readings; an INVALID one counts as blocked, which sent the Bug rules
# the wrong way in 4 of 50 HIL episodes), then decide with it counted as blocked
GRID_INVALID_RETRY_TICKS = 10
TURN_GAIN_PER_S = 4  # wheel speed = gain * error * base/2, capped by the turn action
MIN_TURN_MM_S = 30
MIN_DRIVE_MM_S = 80
DRIVE_GAIN_PER_S = 3  # forward speed = gain * distance, capped by the forward action
STEER_GAIN_PER_S = 3  # yaw rate (mrad/s) = gain * bearing (mrad)
STOP_BURST_TICKS = 3  # zero commands sent after leaving DRIVING when not in lockstep
# Encoder plausibility: a wheel cannot turn faster than MAX_WHEEL_SPEED_MM_S; a
# count difference beyond ENC_JUMP_MARGIN x that (plus a few ticks of slack for
# sampling jitter) over the time since the last sample is a broken or forged
# encoder frame.
ENC_JUMP_MARGIN = 2
ENC_JUMP_SLACK_TICKS = 64
_WHEEL_CIRC_NM = robot_spec.wheel_circumference_nm()


def encoder_jump_limit(dt_us: int) -> int:
    """Largest plausible encoder count change (ticks, either wheel) over dt_us:
    ENC_JUMP_MARGIN x full wheel speed plus ENC_JUMP_SLACK_TICKS; more is a jump.
    (mm/s x us is nm: the distance over the wheel's circumference in nm.)"""
    return (ENC_JUMP_MARGIN * robot_spec.MAX_WHEEL_SPEED_MM_S * dt_us * robot_spec.ENCODER_TICKS_PER_REV
            // _WHEEL_CIRC_NM + ENC_JUMP_SLACK_TICKS)


# Exploration while localising globally (a reactive wander: forward while the front is clear, else turn).
EXPLORE_FORWARD_MM_S = 250
EXPLORE_TURN_MM_S = 160
EXPLORE_CLEAR_FRONT_MM = 450
EXPLORE_CLEAR_DIAGONAL_MM = 80  # a 500 mm corridor leaves ~200 mm; 80 mm on a diagonal is ~160 mm beside the path
EXPLORE_STEER_GAIN = 0.3  # (mm/s) / mm of left-right diagonal difference
EXPLORE_STEER_MM_S = 80
EXPLORE_TIMEOUT_US = 30_000_000

# Grid action (dcol, drow) -> world heading (mrad): rows grow southwards.
_GRID_HEADING = {(1, 0): 0, (0, -1): 1571, (-1, 0): 3142, (0, 1): -1571}


@dataclass
class Inputs:
    """Latest value of every CAN input and the clock time it arrived (None:
    never). The node's receive side fills it; `step` only reads it."""

    ranges_mm: list[int] = field(default_factory=lambda: [robot_spec.RANGE_MAX_MM] * robot_spec.SENSOR_COUNT)
    range_status: list[int] = field(default_factory=lambda: [robot_spec.RANGE_INVALID] * robot_spec.SENSOR_COUNT)
    ranges_us: list[int | None] = field(default_factory=lambda: [None, None])  # one per range frame
    enc_left: int = 0
    enc_right: int = 0
    enc_us: int | None = None
    bumper: bool = False
    bumper_events: int = 0
    bumper_us: int | None = None
    driver_state: int = 0
    driver_errors: int = 0
    driver_estop: bool = False
    driver_left_mm_s: int = 0
    driver_right_mm_s: int = 0
    driver_us: int | None = None
    estop: bool = False  # an EStop frame from another node engaged it
    estop_us: int | None = None
    # rolling counter of the last frame per sensor input ("ranges0", "ranges1",
    # "enc", "bumper"); absent: the sender carries none (only stamps count then)
    counters: dict[str, int] = field(default_factory=dict)

    def note_counter(self, key: str, value: int | None) -> None:
        """Record a sensor frame's rolling counter (the node's receive side)."""
        if value is not None:
            self.counters[key] = value

    def copy(self) -> Inputs:
        return replace(self, ranges_mm=list(self.ranges_mm), range_status=list(self.range_status),
                       ranges_us=list(self.ranges_us), counters=dict(self.counters))


@dataclass(frozen=True)
class MotorCommand:
    left_mm_s: int
    right_mm_s: int
    counter: int


@dataclass(frozen=True)
class Heartbeat:
    state: int
    mode: int
    armed: bool
    policy_loaded: bool
    goal_active: bool
    errors: int
    counter: int


@dataclass(frozen=True)
class Outputs:
    """What one tick sends: a motor command (None: send nothing, let the
    driver's watchdog hold the wheels) and the controller heartbeat."""

    motor: MotorCommand | None
    heartbeat: Heartbeat


@dataclass(frozen=True)
class Transition:
    t_us: int
    src: CtrlState
    dst: CtrlState
    cause: str


@dataclass
class _Primitive:
    """One cell step: turn to `heading_mrad`, then drive to `target`."""

    target: tuple[int, int]
    heading_mrad: int
    turning: bool = True


class Controller:
    """The control state machine; implements vehicle.VehicleControl."""

    def __init__(self, config: VehicleConfig | None = None, policy: Policy | None = None, *,
                 start_pose_mm: tuple[int, int, int] = (0, 0, 0), lockstep: bool = False,
                 localise: bool = True, localiser_config: LocaliserConfig | None = None) -> None:
        self.cfg = config or VehicleConfig()
        self._lock = threading.RLock()
        self.lockstep = lockstep
        self.policy = policy
        self.last_known_good: Policy | None = None
        self.odom = Odometry(*start_pose_mm, counter_bits=ENCODER_BITS)
        self.watchdog = MotorWatchdog(self.cfg.motor_timeout_ms * 1000)
        self.estop_latch = EStopLatch()
        self.state = CtrlState.BOOT
        self.mode = Mode.HOLD
        self.armed = False
        self.failsafe = False
        self.fault = ""
        self.goal: tuple[int, int] | None = None
        self._goal_index = 0
        self.mission: list[tuple[int, int]] = []
        self.mission_seq = 0
        self._prim: _Primitive | None = None
        self._events: deque[VehicleEvent] = deque(maxlen=256)
        self.progress = ProgressWatch()  # STATUSTEXT when the way is blocked
        self.transitions: deque[Transition] = deque(maxlen=1024)
        self._now = 0
        self._inputs = Inputs()
        self._last_enc_us: int | None = None
        self.encoder_jumps = 0  # implausible encoder samples (not integrated)
        # key -> (counter, stamp of the frame where it last advanced): frozen senders
        self._counter_seen: dict[str, tuple[int, int | None]] = {}
        self._stop_burst = 0
        self._driving_since_us = 0
        self._cmd_counter = 0
        self._hb_counter = 0
        self._ticks = 0
        self._errors = 0
        self._state_index = -1
        self._action = -1
        self._q_row: tuple[int, ...] = ()
        # sector-memory policies: the cell-stepped Bug memory of the current goal (reset when the goal or
        # the drive changes)
        self.grid_memory = GridBugMemory()
        self._grid_invalid_ticks = 0  # ticks waited for valid axis readings at this decision
        self._grid_invalid_at = -1
        self._memory_key: tuple[tuple[int, int], int] | None = None
        # sector policies with a map and planner parameters: sub-goals round unmapped obstacles
        self.local: tuple[LocalPlanner, ObstacleMemory, MotionGuard] | None = None
        self._local_for: Policy | None = None
        self._local_key: tuple[tuple[int, int], int] | None = None
        self.target_mm: tuple[int, int] | None = None  # what the policy steered to (None: the goal itself)
        self.tick_overruns = 0
        self.can_errors = 0
        # Monte Carlo localisation on the policy's map (control/localiser.py) when the policy carries one
        self.localise = localise
        self._loc_cfg = localiser_config
        self.loc: Localiser | None = None
        self._explore_until_us: int | None = None  # exploring for global localisation (armed, HOLD)
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

    def _stop(self) -> None:
        self.watchdog.stop()
        self._prim = None
        self._stop_burst = STOP_BURST_TICKS

    def _enter_fault(self, cause: str) -> None:
        self.fault = cause
        self._transition(CtrlState.FAULT, cause, SEV_CRITICAL)
        self._event("fault", cause, SEV_CRITICAL)

    def _note_counters(self, inp: Inputs) -> None:
        """Remember when each sensor's rolling counter last advanced."""
        stamps = {"ranges0": inp.ranges_us[0], "ranges1": inp.ranges_us[1], "enc": inp.enc_us,
                  "bumper": inp.bumper_us}
        for key, ctr in inp.counters.items():
            seen = self._counter_seen.get(key)
            if seen is None or seen[0] != ctr:
                self._counter_seen[key] = (ctr, stamps.get(key))

    def _fresh_since(self, inp: Inputs, key: str, stamp: int | None) -> int | None:
        """The input's time for staleness: its stamp, or, while its counter has
        not advanced, the stamp of the frame where it last did (a sender stuck
        re-sending one frame goes stale like a silent one)."""
        seen = self._counter_seen.get(key)
        if seen is not None and inp.counters.get(key) == seen[0]:
            return seen[1] if seen[1] is None or stamp is None else min(stamp, seen[1])
        return stamp

    def _stale_inputs(self, inp: Inputs, now_us: int) -> list[str]:
        tmo = self.cfg.sensor_timeout_ms * 1000
        stale = []
        for name, key, stamp in (("ranges0", "ranges0", inp.ranges_us[0]), ("ranges1", "ranges1", inp.ranges_us[1]),
                                 ("encoders", "enc", inp.enc_us), ("bumper", "bumper", inp.bumper_us)):
            t = self._fresh_since(inp, key, stamp)
            if t is None or now_us - t > tmo:
                stale.append(name if t == stamp else f"{name} frozen")
        return stale

    def _driver_silent(self, inp: Inputs, now_us: int) -> bool:
        return inp.driver_us is None or now_us - inp.driver_us > self.cfg.sensor_timeout_ms * 1000

    def _goal_index_for(self, x_mm: int, y_mm: int, policy: Policy | None = None) -> tuple[int, str]:
        """Goal index of a world point for a cell policy (-1 and a reason if none)."""
        pol = policy or self.policy
        if pol is None or not isinstance(pol.encoder, CellEncoder):  # pol.kind != "cell"
            return 0, ""
        enc = pol.encoder
        col, row = robot_spec.world_to_cell(x_mm, y_mm, enc.height, pol.cell_mm)
        if (col, row) in pol.goals:
            return pol.goals.index((col, row)), ""
        return -1, f"goal cell ({col},{row}) is not a policy target"

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
        self._prim = None
        self.progress.restart()
        if self.state == CtrlState.DRIVING:
            log.info("t=%d us retarget: %s", self._now, cause)
            self._event("info", f"retarget: {cause}")
        else:
            self._transition(CtrlState.DRIVING, cause)

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
                time_us=self._now, state=self.state, mode=self.mode, armed=self.armed,
                failsafe=self.failsafe, fault=self.fault,
                x_mm=x_mm, y_mm=y_mm, heading_mrad=heading_mrad,
                speed_mm_s=self.odom.speed_mm_s, yaw_rate_mrad_s=self.odom.yaw_rate_mrad_s,
                goal_mm=self.goal, distance_to_goal_mm=dist, bearing_to_goal_mrad=bearing,
                ranges_mm=list(inp.ranges_mm), range_status=list(inp.range_status),
                sensors_healthy=not self._stale_inputs(inp, self._now),
                motors_healthy=not self._driver_silent(inp, self._now) and inp.driver_errors == 0,
                bumper=inp.bumper, estop=self.estop_latch.latched or inp.estop or inp.driver_estop,
                state_index=self._state_index, action=self._action, q_row=self._q_row,
                mission_seq=self.mission_seq, mission_count=len(self.mission),
                policy_id=self.policy.policy_id if self.policy else 0,
                policy_crc=self.policy.crc if self.policy else 0,
                map_mm=self._map_mm(),
                ticks=self._ticks, tick_overruns=self.tick_overruns, can_errors=self.can_errors,
                odom_x_mm=self.odom.x_mm, odom_y_mm=self.odom.y_mm, odom_heading_mrad=self.odom.heading_mrad,
                localiser=("off" if self.loc is None else "global" if self.loc.global_mode else "tracking"),
                localised=self.loc is None or self.loc.localised,
                pose_std_mm=(round(std[0]), round(std[1])), pose_std_mrad=round(std[2]))

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
            if self._driver_silent(inp, self._now):
                return False, "motor driver silent"
            if inp.driver_errors:
                return False, f"motor driver errors 0x{inp.driver_errors:02x}"
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
            if mode == Mode.MANUAL:
                return False, "MANUAL unsupported: policy drives only"
            self.mode = mode
            if mode == Mode.HOLD and self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                self.goal = None
                self._transition(CtrlState.HOLD, "mode HOLD")
            elif mode == Mode.AUTO and self.armed and self.mission and self.state != CtrlState.FAULT:
                return self._start_mission_locked()
            return True, ""

    def set_goal(self, x_mm: int, y_mm: int) -> tuple[bool, str]:
        with self._lock:
            ok, why = self._can_drive()
            if not ok:
                return False, why
            gi, why = self._goal_index_for(int(x_mm), int(y_mm))
            if gi < 0:
                return False, why
            self.mode = Mode.GUIDED
            self._start_driving((int(x_mm), int(y_mm)), gi, f"goal ({int(x_mm)},{int(y_mm)}) mm")
            return True, ""

    def set_mission(self, waypoints_mm: list[tuple[int, int]]) -> tuple[bool, str]:
        with self._lock:
            wps = [(int(x), int(y)) for x, y in waypoints_mm]
            if self.policy is not None:
                for i, (x, y) in enumerate(wps):
                    gi, why = self._goal_index_for(x, y)
                    if gi < 0:
                        return False, f"item {i}: {why}"
            self.mission = wps
            self.mission_seq = 0
            if self.mode == Mode.AUTO and self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                self.goal = None
                self._transition(CtrlState.HOLD, "mission replaced")
            return True, ""

    def set_mission_current(self, seq: int) -> tuple[bool, str]:
        with self._lock:
            if not 0 <= seq < len(self.mission):
                return False, f"mission item {seq} outside 0..{len(self.mission) - 1}"
            self.mission_seq = seq
            if self.mode == Mode.AUTO and self.state == CtrlState.DRIVING:
                x, y = self.mission[seq]
                gi, _ = self._goal_index_for(x, y)
                self._start_driving((x, y), gi, f"mission item {seq}")
            return True, ""

    def _start_mission_locked(self) -> tuple[bool, str]:
        ok, why = self._can_drive()
        if not ok:
            return False, why
        if not self.mission:
            return False, "no mission loaded"
        if self.mission_seq >= len(self.mission):
            self.mission_seq = 0
        x, y = self.mission[self.mission_seq]
        gi, why = self._goal_index_for(x, y)
        if gi < 0:
            return False, f"item {self.mission_seq}: {why}"
        self.mode = Mode.AUTO
        self._start_driving((x, y), gi, f"mission item {self.mission_seq}")
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
            if not self.armed or action == FailsafeAction.NONE:
                return
            if action == FailsafeAction.DISARM:
                self.disarm()
            elif self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                self.mode = Mode.HOLD
                self.goal = None
                self._transition(CtrlState.HOLD, "GCS failsafe", SEV_CRITICAL)

    def check_config(self, cfg: VehicleConfig) -> tuple[bool, str]:
        """Refuse a config the active policy does not fit (policy.config_mismatch)."""
        with self._lock:
            if self.policy is None:
                return True, ""
            why = config_mismatch(self.policy, cfg.control_period_us, cfg.cell_size_mm)
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
                self.policy = None

    def activate_policy(self, path: str) -> tuple[bool, str]:
        """Validate a policy file with the loader and swap it in between two
        ticks; the one it replaces is kept as `last_known_good`."""
        with self._lock:
            if self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                return False, "refused while driving: stop first"
        try:
            new = load_policy(path)  # file I/O outside the lock: ticks keep running
        except PolicyError as exc:
            return False, f"policy rejected: {exc}"
        return self.activate_loaded(new)

    def activate_loaded(self, new: Policy) -> tuple[bool, str]:
        """Swap in an already validated policy (see activate_policy)."""
        loc = self._new_localiser(new)  # outside the lock (see _new_localiser)
        with self._lock:
            if self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                return False, "refused while driving: stop first"
            why = config_mismatch(new, self.cfg.control_period_us, self.cfg.cell_size_mm)
            if why:
                return False, why
            for i, (x, y) in enumerate(self.mission):
                gi, why = self._goal_index_for(x, y, new)
                if gi < 0:
                    return False, f"mission item {i}: {why}"
            old = self.policy
            self.policy = new
            self._use_localiser(new, loc if loc is not None else self._new_localiser(new))
            if old is not None:
                self.last_known_good = old
            text = f"policy 0x{new.policy_id:08x} {new.kind} active"
            log.info("t=%d us %s", self._now, text)
            self._event("info", text)
            return True, ""

    def revert_policy(self) -> tuple[bool, str]:
        """Swap back to the last-known-good policy."""
        with self._lock:
            if self.last_known_good is None:
                return False, "no last-known-good policy"
            lkg = self.last_known_good
        return self.activate_loaded(lkg)

    def drain_events(self) -> list[VehicleEvent]:
        with self._lock:
            out = list(self._events)
            self._events.clear()
            return out

    def set_pose(self, x_mm: int, y_mm: int, heading_mrad: int) -> None:
        """Set the odometry pose (start pose, or a re-localisation fix)."""
        with self._lock:
            self.odom.reset(int(x_mm), int(y_mm), int(heading_mrad))
            self._last_enc_us = None
            self._prim = None
            if self.loc is not None:
                self.loc.init_pose(int(x_mm), int(y_mm), int(heading_mrad))

    def localise_global(self, explore: bool = True) -> tuple[bool, str]:
        """Forget the pose: particles uniform over the map (global
        localisation). With `explore` and armed in HOLD the robot wanders
        (forward while the front is clear, steering towards the side with
        more room, else turning in place) until the
        localiser has converged, the bumper is pressed, it is disarmed or
        EXPLORE_TIMEOUT_US passes; goals are refused until it is localised."""
        with self._lock:
            if self.loc is None:
                return False, "no map: the active policy carries none (qnav policy attach-map)"
            if self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                return False, "refused while driving: stop first"
            self.loc.init_global()
            self._explore_until_us = self._now + EXPLORE_TIMEOUT_US if explore else None
            self._event("info", "global localisation started" + (", exploring" if explore else ""))
            return True, ""

    def _explore(self, inp: Inputs, now_us: int) -> None:
        """One tick of the wander that feeds global localisation (HOLD, armed)."""
        assert self._explore_until_us is not None and self.loc is not None
        done = ""
        if not self.loc.global_mode:
            done = "localised"
        elif not self.armed or self.state != CtrlState.HOLD or inp.bumper:
            done = "exploration stopped"
        elif now_us >= self._explore_until_us:
            done = "exploration timed out, not localised"
        if done:
            self._explore_until_us = None
            self._stop()
            self._event("info", done, SEV_INFO if done == "localised" else SEV_WARNING)
            return

        def rng(k: int) -> int:
            st = inp.range_status[k]
            return robot_spec.RANGE_MAX_MM if st == robot_spec.RANGE_TOO_FAR else (
                inp.ranges_mm[k] if st == robot_spec.RANGE_VALID else 0)

        front = rng(0)
        left, right = rng(1), rng(7)
        if front > EXPLORE_CLEAR_FRONT_MM and min(left, right) > EXPLORE_CLEAR_DIAGONAL_MM:
            # steer towards the side with more room (keeps it centred in a 500 mm corridor)
            steer = max(-EXPLORE_STEER_MM_S, min(EXPLORE_STEER_MM_S, (left - right) * EXPLORE_STEER_GAIN))
            self.watchdog.feed(now_us, round(EXPLORE_FORWARD_MM_S - steer), round(EXPLORE_FORWARD_MM_S + steer))
        else:
            self.watchdog.feed(now_us, -EXPLORE_TURN_MM_S, EXPLORE_TURN_MM_S)

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
            self._note_counters(inp)
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
            errors = self._safety(inp, now_us)
            if self.state == CtrlState.GOAL_REACHED:
                self._after_goal()
            if self.state == CtrlState.DRIVING:
                self._drive(inp, now_us)
            elif self._explore_until_us is not None:
                self._explore(inp, now_us)
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
        dt_us = max(0, inp.enc_us - self._last_enc_us)
        limit = encoder_jump_limit(dt_us)
        for side, ticks in (("left", d[0]), ("right", d[1])):
            if abs(ticks) > limit:
                return f"encoder jump: {side} {ticks} ticks/{dt_us // 1000} ms (max {limit})"
        return ""

    def _safety(self, inp: Inputs, now_us: int) -> int:
        errors = 0
        estop = inp.estop or inp.driver_estop
        stale = self._stale_inputs(inp, now_us)
        silent = self._driver_silent(inp, now_us)
        if stale:
            errors |= ERR_SENSOR_STALE
        if silent:
            errors |= ERR_DRIVER_SILENT
        if inp.driver_errors:
            errors |= ERR_DRIVER_FAULT
        if inp.bumper:
            errors |= ERR_BUMPER
        if self.policy is None:
            errors |= ERR_NO_POLICY
        if self.failsafe:
            errors |= ERR_FAILSAFE
        if self.armed:
            if estop and self.estop_latch.trip():
                self._enter_fault("e-stop engaged")
            if self.state != CtrlState.FAULT:
                if stale:
                    self._enter_fault(f"sensor data stale: {','.join(stale)}")
                elif silent:
                    self._enter_fault("motor driver status stale")
                elif inp.driver_errors:
                    self._enter_fault(f"motor driver fault 0x{inp.driver_errors:02x}")
                elif self._driver_watchdog_tripped(inp):
                    self._enter_fault("motor driver watchdog tripped while driving")
            if inp.bumper and self.state in (CtrlState.DRIVING, CtrlState.GOAL_REACHED):
                self.goal = None
                self.mode = Mode.HOLD
                self._transition(CtrlState.HOLD, "bumper pressed", SEV_WARNING)
        if self.estop_latch.latched:
            errors |= ERR_ESTOP
        if self.fault.startswith("localisation"):
            errors |= ERR_LOCALISATION
        self._errors = errors
        return errors

    def _driver_watchdog_tripped(self, inp: Inputs) -> bool:
        """The driver stopped the wheels for want of commands although we are
        DRIVING (commands lost on the way). Its status may still show the
        HOLD-time watchdog stop for a tick or two after DRIVING starts."""
        grace_us = 2 * self.cfg.control_period_us
        return (self.state == CtrlState.DRIVING and inp.driver_state == MOTOR_WATCHDOG_STOP
                and inp.driver_us is not None and inp.driver_us - self._driving_since_us > grace_us)

    def _after_goal(self) -> None:
        if self.mode == Mode.AUTO and self.mission_seq + 1 < len(self.mission):
            self.mission_seq += 1
            x, y = self.mission[self.mission_seq]
            gi, why = self._goal_index_for(x, y)
            if gi >= 0:
                self.goal = (x, y)
                self._goal_index = gi
                self._prim = None
                self._transition(CtrlState.DRIVING, f"next mission item {self.mission_seq}")
                return
            self._event("refusal", f"item {self.mission_seq}: {why}", SEV_WARNING)
        cause = "mission complete" if self.mode == Mode.AUTO else "goal reached"
        if self.mode == Mode.AUTO:
            self.mode = Mode.HOLD
        self.goal = None
        self._transition(CtrlState.HOLD, cause)

    def _drive(self, inp: Inputs, now_us: int) -> None:
        assert self.goal is not None and self.policy is not None
        dist, bearing = self.nav.goal_vector(*self.goal)
        if dist <= self.cfg.goal_tolerance_mm:
            self._transition(CtrlState.GOAL_REACHED, f"goal reached, {dist} mm off")
            if self.mode == Mode.AUTO:
                self._event("mission_item_reached", f"reached item {self.mission_seq}",
                            seq=self.mission_seq)
            return
        stalled = self.progress.update(now_us, self.goal, dist)
        if stalled:
            item = f"item {self.mission_seq}: " if self.mode == Mode.AUTO else ""
            self._event("info", item + stalled, SEV_WARNING)
        pol = self.policy
        if isinstance(pol.encoder, SectorEncoder):
            local = pol.local_planner is not None and pol.map_grid is not None
            if local:
                bearing = self._local_bearing(pol, inp, now_us, bearing)
            s = pol.encoder.encode(bearing, inp.ranges_mm, inp.range_status)
            a = pol.best_action(s)
            if local and self.local is not None:
                x, y, _ = self.nav.pose_mm()
                a = self.local[2].action(now_us, x, y, a, bearing, inp.ranges_mm, inp.range_status,
                                         self.local[1])
            left, right = robot_spec.ACTION_WHEEL_SPEEDS_MM_S[a]
            self._state_index, self._action, self._q_row = s, a, tuple(pol.row(s))
        else:
            wheels = self._cell_primitive()
            if wheels is None:
                return
            left, right = wheels
        pct = self.cfg.speed_scale_pct
        left, right = clamp_speeds(left * pct // 100, right * pct // 100, self.cfg.max_wheel_speed_mm_s)
        self.watchdog.feed(now_us, left, right)

    def _statuses_for_localiser(self, inp: Inputs) -> list[int]:
        """The range statuses the localiser weighs. With a local planner on a tracked pose, readings
        the map does not explain there (unmapped obstacles, firmware_py.localplan) are withheld as
        invalid: each lowers every particle's weight, and a few together started augmented MCL's
        random-particle recovery, which in a map of look-alike places jumped the estimate (HIL,
        3 discs + 2 movers: 0.80 success against 0.94 on odometry, the lost pose every time)."""
        pol, loc = self.policy, self.loc
        status = list(inp.range_status)
        if pol is None or pol.local_planner is None or pol.map_grid is None or loc is None or not loc.localised:
            return status
        x, y, heading = loc.pose_mm()
        um = unmapped_readings(pol.map_grid, x, y, heading, inp.ranges_mm, status, pol.local_planner.margin_mm)
        return [robot_spec.RANGE_INVALID if u >= 0 else st for u, st in zip(um, status, strict=True)]

    def _local_bearing(self, pol: Policy, inp: Inputs, now_us: int, bearing: int) -> int:
        """The bearing to the local planner's target for this tick (firmware_py.localplan):
        the goal's own bearing until an unmapped obstacle is in the way."""
        assert pol.local_planner is not None and pol.map_grid is not None and self.goal is not None
        if self.local is None or self._local_for is not pol:
            cfg = pol.local_planner
            self.local = (LocalPlanner(pol.map_grid, cfg), ObstacleMemory(cfg), MotionGuard(cfg))
            self._local_for = pol
        planner, memory, guard = self.local
        key = (self.goal, self._driving_since_us)
        if key != self._local_key:  # a new goal (mission item, drive): straight at it until blocked
            planner.reset()
            if self._local_key is None or key[1] != self._local_key[1]:
                guard.reset()  # a new drive, not a new mission item (the twin: one guard per episode)
            self._local_key = key
        x, y, heading = self.nav.pose_mm()
        memory.observe(pol.map_grid, x, y, heading, inp.ranges_mm, inp.range_status, now_us)
        tx, ty = planner.target(x, y, self.goal, memory)
        if not planner.detouring:
            self.target_mm = None
            return bearing
        self.target_mm = (round(tx), round(ty))
        return self.nav.goal_vector(*self.target_mm)[1]

    def _cell_primitive(self, depth: int = 0) -> tuple[int, int] | None:
        """The cell motion primitive's executor: when no step is open, the
        policy's decision (`_cell_decision` for a cell policy,
        `_grid_decision` for a sector-memory one) names the next cell
        centre and grid heading; then turn in place, drive there, repeat."""
        pol = self.policy
        assert pol is not None and self.goal is not None  # called from _drive
        x, y, heading = self.nav.pose_mm()
        if self._prim is None:
            step = (self._grid_decision(x, y, heading) if isinstance(pol.encoder, GridBugEncoder)
                    else self._cell_decision(x, y, heading))
            if step is None:
                return None
            self._prim = _Primitive(*step)
        prim = self._prim
        half_base = robot_spec.WHEEL_BASE_MM // 2
        turn_cap = abs(robot_spec.ACTION_WHEEL_SPEEDS_MM_S[1][1])
        if prim.turning:
            err = wrap_mrad(prim.heading_mrad - heading)
            if abs(err) > TURN_TOLERANCE_MRAD:
                w = TURN_GAIN_PER_S * abs(err) * half_base // 1000
                w = max(MIN_TURN_MM_S, min(turn_cap, w))
                return (-w, w) if err > 0 else (w, -w)
            prim.turning = False
        dist, bearing = self.nav.goal_vector(*prim.target)
        if dist <= ARRIVE_TOLERANCE_MM or (abs(bearing) > 1571 and dist < pol.cell_mm // 2):
            self._prim = None  # arrived (or just past it): re-localise from odometry
            return self._cell_primitive(depth + 1) if depth == 0 else (0, 0)
        if abs(bearing) > RETURN_TO_TURN_MRAD:
            prim.turning = True
            prim.heading_mrad = wrap_mrad(heading + bearing)
            return (0, 0)
        fwd_cap = robot_spec.ACTION_WHEEL_SPEEDS_MM_S[0][0]
        v = max(MIN_DRIVE_MM_S, min(fwd_cap, DRIVE_GAIN_PER_S * dist))
        dv = STEER_GAIN_PER_S * bearing * half_base // 1000
        return (v - dv, v + dv)

    def _cell_decision(self, x: int, y: int, heading: int) -> tuple[tuple[int, int], int] | None:
        """Cell policy: localise the cell, greedy grid action -> (next cell centre, its heading)."""
        pol = self.policy
        assert pol is not None and self.goal is not None
        enc = pol.encoder
        assert isinstance(enc, CellEncoder)  # _drive: not a sector policy
        col, row = robot_spec.world_to_cell(x, y, enc.height, pol.cell_mm)
        if not (0 <= col < enc.width and 0 <= row < enc.height):
            self.fault = f"localisation: cell ({col},{row}) off the map"
            self._enter_fault(self.fault)
            return None
        goal_cell = robot_spec.world_to_cell(*self.goal, enc.height, pol.cell_mm)
        if (col, row) == goal_cell:
            _, b = self.nav.goal_vector(*self.goal)
            return self.goal, wrap_mrad(heading + b)
        s = enc.encode(col, row, self._goal_index)
        a = pol.best_action(s)
        dc, dr = robot_spec.CELL_ACTION_DELTAS[a]
        self._state_index, self._action, self._q_row = s, a, tuple(pol.row(s))
        return robot_spec.cell_center_mm(col + dc, row + dr, enc.height, pol.cell_mm), _GRID_HEADING[(dc, dr)]

    def _grid_decision(self, x: int, y: int, heading: int) -> tuple[tuple[int, int], int]:
        """sector-memory policy (firmware_py.gridbug): at the centre of
        the current cell (world lattice of the encoder's cell size) and facing
        a grid direction, encode (Bug memory, goal vector from the cell
        centre, the four neighbours' sensors) -> greedy relative move -> the
        next cell centre and its heading. Off the centre it first drives
        there, off a grid direction it first turns to the nearest one (a
        step to its own position), so the sensors look along the grid."""
        pol = self.policy
        assert pol is not None and self.goal is not None
        enc = pol.encoder
        assert isinstance(enc, GridBugEncoder)
        c = enc.cell_mm
        centre = ((x // c) * c + c // 2, (y // c) * c + c // 2)
        gx, gy = self.goal
        if (gx // c, gy // c) == (x // c, y // c):  # the goal's own cell: straight to it
            _, b = self.nav.goal_vector(gx, gy)
            return self.goal, wrap_mrad(heading + b)
        key = (self.goal, self._driving_since_us)
        if key != self._memory_key:  # a new goal (or mission item, or a new drive): forget the wall
            self.grid_memory.reset(grid_dir_of(heading))
            self._memory_key = key
        if abs(centre[0] - x) + abs(centre[1] - y) > 2 * ARRIVE_TOLERANCE_MM:
            return centre, wrap_mrad(heading + self.nav.goal_vector(*centre)[1])
        physical = grid_dir_of(heading)
        if abs(wrap_mrad(heading - DIR_HEADING_MRAD[physical])) > 2 * TURN_TOLERANCE_MRAD:
            return (x, y), DIR_HEADING_MRAD[physical]
        status = self._inputs.range_status
        if any(status[2 * k] == robot_spec.RANGE_INVALID for k in range(4)):
            if self._now != self._grid_invalid_at:  # a dropout: stand still and read again next tick
                self._grid_invalid_ticks += 1
                self._grid_invalid_at = self._now
            if self._grid_invalid_ticks <= GRID_INVALID_RETRY_TICKS:
                return (x, y), heading
        self._grid_invalid_ticks = 0
        s = enc.encode(self.grid_memory, gx - centre[0], gy - centre[1], physical,
                       self._inputs.ranges_mm, status)
        a = pol.best_action(s)
        d = self.grid_memory.note_move(a)
        self._state_index, self._action, self._q_row = s, a, tuple(pol.row(s))
        dcol, drow = DIR_VECTORS[d]
        return (centre[0] + dcol * c, centre[1] + drow * c), DIR_HEADING_MRAD[d]

    def _outputs(self, now_us: int, tick: int | None, errors: int) -> Outputs:
        left, right = self.watchdog.output(now_us)
        left, right = clamp_speeds(left, right, self.cfg.max_wheel_speed_mm_s)
        if tick is not None:
            counter = tick & 0xFFFFFF
        else:
            self._cmd_counter = (self._cmd_counter + 1) & 0xFFFFFF
            counter = self._cmd_counter
        moving = self.state == CtrlState.DRIVING or self._explore_until_us is not None
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
        return Outputs(motor=motor, heartbeat=hb)
