"""What the controller reads and writes each tick: the latest CAN inputs with their
arrival times (`Inputs`, filled by the node's receive side), and the motor
command and heartbeat one tick sends (`Outputs`); the heartbeat's error bits;
the record of a state transition. Plain data, no behaviour beyond copying.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from firmware_py import robot_spec
from firmware_py.layout import Layout
from firmware_py.vehicle import CtrlState

# Ctrl_Errors bit field of the controller heartbeat (docs/can-protocol.md).
ERR_SENSOR_STALE = 1 << 0
ERR_DRIVER_FAULT = 1 << 1
ERR_ESTOP = 1 << 2
ERR_BUMPER = 1 << 3
ERR_NO_POLICY = 1 << 4
ERR_DRIVER_SILENT = 1 << 5
ERR_FAILSAFE = 1 << 6
ERR_LOCALISATION = 1 << 7


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
    bumper_us: int | None = None
    driver_state: int = 0
    driver_errors: int = 0
    driver_estop: bool = False
    driver_us: int | None = None
    driver_detail: str = ""  # a drive backend's words for what is wrong (names the axis/ESC), '' when nothing
    arm_block: str = ""  # a backend's words for why the robot must not arm (a DroneCAN node-id collision), ''
    estop: bool = False  # an EStop frame from another node engaged it
    estop_us: int | None = None
    # the power board's BatteryStatus (none on a robot without one: telemetry says unknown)
    battery_mv: int = 0
    battery_ma: int = 0
    battery_pct: int = -1
    battery_us: int | None = None
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


def sensor_view(inp: Inputs, layout: Layout) -> Inputs:
    """The snapshot as the controller's parts read it: one reading per sensor of the layout (the robot
    profile's, in its order; a sensor not heard yet INVALID), a VALID reading beyond its sensor's
    maximum range INVALID (a broken or forged frame). The snapshot itself when nothing changes."""
    st = layout.plausible(inp.ranges_mm, inp.range_status)
    n = layout.count
    if st == inp.range_status and len(inp.ranges_mm) == n:
        return inp
    rs = list(inp.ranges_mm[:n]) + [0] * (n - len(inp.ranges_mm))
    return replace(inp, ranges_mm=rs, range_status=st)


BATTERY_TIMEOUT_US = 5_000_000  # the power board reports at 2 Hz


def battery_fields(inp: Inputs, now_us: int) -> dict[str, int]:
    """The last BatteryStatus, or unknown ({}) when none came within BATTERY_TIMEOUT_US (a board that
    fell silent must not show a full battery forever)."""
    if inp.battery_us is None or now_us - inp.battery_us > BATTERY_TIMEOUT_US:
        return {}
    return {"battery_mv": inp.battery_mv, "battery_ma": inp.battery_ma, "battery_pct": inp.battery_pct}


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
    drive_enabled: bool = False  # the controller wants the wheels powered (driving, exploring, Manual)


@dataclass(frozen=True)
class Transition:
    t_us: int
    src: CtrlState
    dst: CtrlState
    cause: str


def error_bits(inp: Inputs, *, stale: bool, driver_silent: bool, no_policy: bool, failsafe: bool,
               estop_latched: bool, localisation_fault: bool) -> int:
    """The heartbeat's Ctrl_Errors field for one tick."""
    bits = ((ERR_SENSOR_STALE, stale), (ERR_DRIVER_SILENT, driver_silent), (ERR_DRIVER_FAULT, bool(inp.driver_errors)),
            (ERR_BUMPER, inp.bumper), (ERR_NO_POLICY, no_policy), (ERR_FAILSAFE, failsafe),
            (ERR_ESTOP, estop_latched), (ERR_LOCALISATION, localisation_fault))
    return sum(bit for bit, on in bits if on)
