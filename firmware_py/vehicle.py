"""The seam between the controller and the robot's MAVLink node.

The controller (`firmware_py.control.controller`) implements `VehicleControl`; the MAVLink node
(params, commands, missions, telemetry, FTP activation) only talks to the vehicle through it. Both
sides share `VehicleConfig` (the tunables the parameter table maps onto) and the enums below.

Modes are numbered as ArduPilot Rover numbers its custom_mode so stock ground stations show the
right names.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Protocol

from firmware_py import robot_spec


class Mode(IntEnum):
    """HEARTBEAT custom_mode, ArduPilot Rover numbering."""

    MANUAL = 0
    HOLD = 4
    AUTO = 10
    GUIDED = 15


class CtrlState(IntEnum):
    """Controller state machine (see docs/architecture.md)."""

    BOOT = 0
    STANDBY = 1  # disarmed
    HOLD = 2  # armed, no goal
    DRIVING = 3
    GOAL_REACHED = 4
    FAULT = 5
    MANUAL = 6  # reported only (status, telemetry CTRL_ST): armed in Manual, the sticks drive; the machine is in HOLD


class FailsafeAction(IntEnum):
    NONE = 0
    HOLD = 1
    DISARM = 2


@dataclass
class VehicleConfig:
    """Controller tunables; every field is a MAVLink parameter (see params)."""

    control_rate_hz: int = robot_spec.CONTROL_RATE_HZ
    sensor_timeout_ms: int = 250
    motor_timeout_ms: int = 200
    max_wheel_speed_mm_s: int = robot_spec.MAX_WHEEL_SPEED_MM_S
    speed_scale_pct: int = 100
    goal_tolerance_mm: int = robot_spec.GOAL_TOLERANCE_MM
    gcs_timeout_ms: int = 5000
    gcs_failsafe_action: int = FailsafeAction.HOLD
    origin_lat_e7: int = 473_977_420  # a field near Zurich, so ground-station maps show the robot
    origin_lon_e7: int = 85_455_940
    origin_alt_mm: int = 408_000
    cell_size_mm: int = robot_spec.DEFAULT_CELL_SIZE_MM
    # the collision monitor under every command (control/collision.py): no straight motion toward a
    # read point nearer than stop, slow_pct of it nearer than slow (0: that zone off)
    collision_stop_mm: int = 50
    collision_slow_mm: int = 200
    collision_slow_pct: int = 50
    # a drive that neither gets closer to its goal nor moves for this long (robot clock) is reported
    # and held (control/progress.StallWatch; 0: off)
    nav_stall_s: int = 20

    @property
    def control_period_us(self) -> int:
        """The control period this config runs at (robot_spec.control_period_us)."""
        return robot_spec.control_period_us(self.control_rate_hz)


@dataclass
class VehicleStatus:
    """Snapshot of the vehicle for telemetry (one per control tick at most)."""

    time_us: int = 0
    state: CtrlState = CtrlState.BOOT
    mode: Mode = Mode.HOLD
    armed: bool = False
    failsafe: bool = False
    fault: str = ""
    x_mm: int = 0
    y_mm: int = 0
    heading_mrad: int = 0
    speed_mm_s: int = 0
    yaw_rate_mrad_s: int = 0
    goal_mm: tuple[int, int] | None = None
    distance_to_goal_mm: int = 0
    bearing_to_goal_mrad: int = 0  # relative to the heading, CCW positive
    ranges_mm: list[int] = field(default_factory=lambda: [0] * robot_spec.SENSOR_COUNT)
    range_status: list[int] = field(default_factory=lambda: [robot_spec.RANGE_INVALID] * robot_spec.SENSOR_COUNT)
    # where each reading looks (CCW from the heading, the robot profile's order) and the sensors' reach
    range_angles_mrad: tuple[int, ...] = robot_spec.SENSOR_ANGLES_MRAD
    range_max_mm: int = robot_spec.RANGE_MAX_MM
    sensors_healthy: bool = False
    motors_healthy: bool = False
    bumper: bool = False
    estop: bool = False
    state_index: int = -1
    action: int = -1
    q_row: tuple[int, ...] = ()
    mission_seq: int = 0
    mission_count: int = 0
    policy_id: int = 0
    policy_crc: int = 0
    map_mm: tuple[int, int] | None = None  # the robot's map extent (world mm, x east, y north, from 0)
    ticks: int = 0
    tick_overruns: int = 0
    can_errors: int = 0
    # x_mm/y_mm/heading_mrad above are the pose the robot drives by (the localiser's when it runs);
    # the raw dead-reckoning pose stays here for comparison
    odom_x_mm: int = 0
    odom_y_mm: int = 0
    odom_heading_mrad: int = 0
    localiser: str = "off"  # "off" (no map: odometry), "tracking", "global"
    localised: bool = True
    pose_std_mm: tuple[int, int] = (0, 0)  # 1-sigma of x, y
    pose_std_mrad: int = 0  # 1-sigma of the heading
    # the power board's last BatteryStatus (battery_pct -1: none heard; MAVLink says "unknown")
    battery_mv: int = 0
    battery_ma: int = 0
    battery_pct: int = -1


@dataclass(frozen=True)
class VehicleEvent:
    """Something the ground station should hear about once.

    kind: "transition" | "fault" | "refusal" | "info" (-> STATUSTEXT) or
    "mission_item_reached" (-> MISSION_ITEM_REACHED, `seq` set).
    """

    kind: str
    text: str = ""
    seq: int = -1
    severity: int = 6  # MAV_SEVERITY_INFO


ACTIVATION_TIMEOUT_S = 20.0  # a policy not ready by then (its localiser still building) is refused


class PendingActivation:
    """A policy or map activation whose slow part (building the localiser's field for a new map)
    runs on a worker thread: the link thread polls `result()` (None until done) and answers the client
    then; the old policy and map drive meanwhile. `cancel()` (the link gave up waiting) and the
    worker's `claim()` (taken under the controller's lock, just before the swap) exclude each other:
    once cancelled, the worker swaps nothing in; once claimed, `cancel()` returns False and the
    result, due in a moment, stands."""

    def __init__(self) -> None:
        self._done = threading.Event()
        self._result: tuple[bool, str] = (False, "not finished")
        self._lock = threading.Lock()
        self.cancelled = False
        self._claimed = False

    def finish(self, ok: bool, reason: str) -> None:
        self._result = (ok, reason)
        self._done.set()

    def result(self) -> tuple[bool, str] | None:
        return self._result if self._done.is_set() else None

    def wait(self, timeout_s: float | None = None) -> tuple[bool, str]:
        if not self._done.wait(timeout_s):
            if self.cancel():
                return False, f"activation not ready within {timeout_s:g} s"
            self._done.wait()  # claimed: the swap is under way, its result a moment off
        return self._result

    def cancel(self) -> bool:
        """Drop the activation unless the worker already claimed it: True when it will swap nothing in."""
        with self._lock:
            if self._claimed:
                return False
            self.cancelled = True
            return True

    def claim(self) -> bool:
        """The worker's last step before its swap: False when the activation was cancelled."""
        with self._lock:
            if self.cancelled:
                return False
            self._claimed = True
            return True


class VehicleControl(Protocol):
    """What the MAVLink node may ask of the controller. Every command returns
    (accepted, reason); a refusal's reason becomes a STATUSTEXT."""

    def status(self) -> VehicleStatus: ...
    def arm(self) -> tuple[bool, str]: ...
    def disarm(self) -> tuple[bool, str]: ...
    def set_mode(self, mode: Mode) -> tuple[bool, str]: ...
    def set_goal(self, x_mm: int, y_mm: int) -> tuple[bool, str]: ...
    def set_mission(self, waypoints_mm: list[tuple[int, int]]) -> tuple[bool, str]: ...
    def set_mission_current(self, seq: int) -> tuple[bool, str]: ...
    def start_mission(self) -> tuple[bool, str]: ...
    def set_failsafe(self, active: bool) -> None: ...
    def manual_control(self, x: int, r: int, now_us: int) -> bool:
        """A MANUAL_CONTROL sample (x forward, r clockwise, -1000..1000); False if out of range."""
        ...
    def check_config(self, cfg: VehicleConfig) -> tuple[bool, str]:
        """Would `cfg` keep the active policy usable (its control period, and
        a cell policy's cell size)? Asked before a parameter change is stored."""
        ...
    def apply_config(self, cfg: VehicleConfig) -> None: ...
    def activate_policy(self, path: str) -> tuple[bool, str]: ...
    def begin_activation(self, path: str) -> tuple[bool, str] | PendingActivation:
        """`activate_policy` that returns at once: a PendingActivation while the
        slow part runs off the caller's thread (the FTP server's hook)."""
        ...
    def localise_global(self, explore: bool = True) -> tuple[bool, str]:
        """Forget the pose and find it on the policy's map (exploring when
        armed in HOLD with `explore`); goals are refused until localised."""
        ...
    def drain_events(self) -> list[VehicleEvent]: ...
