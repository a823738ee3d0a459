"""The robot's physical contract, defined once.

Geometry, sensor layout, control period and the action -> wheel-speed table. The training twin
(ground_station), the pymunk plant (sim_bridge) and the controller (firmware_py) all import these
numbers; nothing redefines them.

Units are integers in the control path: millimetres, mm/s, milliradians, microseconds. Float views
(metres, radians) are derived helpers for the ground station and sim.

World frame (shared by maps, sim, odometry and MAVLink conversion): x to the east along map columns,
y to the north, so map row 0 (the first text row of a MovingAI file) is the northernmost row.
Heading is measured counter-clockwise from +x (east). A cell (col, row) of an H-row map with cell
size c has its centre at x = (col + 0.5) * c, y = (H - row - 0.5) * c.
"""

from __future__ import annotations

import math

# --- body -------------------------------------------------------------------
ROBOT_RADIUS_MM = 150
WHEEL_BASE_MM = 260  # distance between the wheel contact points
WHEEL_RADIUS_MM = 40
ENCODER_TICKS_PER_REV = 2048
MAX_WHEEL_SPEED_MM_S = 600  # hard limit, commands are clamped to it

# --- timing -----------------------------------------------------------------
# The control rate is the one owner of the control period: its default and allowed range are defined
# here, and `VehicleConfig.control_rate_hz`, the CTRL_RATE_HZ parameter and `qnav-robot --rate` all
# take them from here. A policy file records the period it was trained for and the robot refuses a
# policy whose period differs from `control_period_us(its rate)`.
CONTROL_RATE_HZ = 20  # default
CONTROL_RATE_MIN_HZ = 1
CONTROL_RATE_MAX_HZ = 100


def wheel_circumference_nm(wheel_radius_mm: int = WHEEL_RADIUS_MM) -> int:
    """The wheel's circumference in nanometres (integer): where pi enters the
    integer odometry and the encoder plausibility limit, computed once."""
    return round(2 * math.pi * wheel_radius_mm * 1_000_000)


def control_period_us(rate_hz: int) -> int:
    """The control period (us) at `rate_hz`; the one place it is computed."""
    return 1_000_000 // max(1, rate_hz)


def control_rate_error(rate_hz: int) -> str:
    """Why `rate_hz` is not an allowed control rate ('' if it is)."""
    if not CONTROL_RATE_MIN_HZ <= rate_hz <= CONTROL_RATE_MAX_HZ:
        return f"expected {CONTROL_RATE_MIN_HZ}..{CONTROL_RATE_MAX_HZ} Hz"
    return ""


CONTROL_PERIOD_US = control_period_us(CONTROL_RATE_HZ)  # the default; training and the sim run at it
PHYSICS_DT_US = 5_000  # the control period is an integer multiple of it
assert CONTROL_PERIOD_US % PHYSICS_DT_US == 0

# --- range sensors ----------------------------------------------------------
# One range sensor per sector, angles CCW from the heading (mrad). Index order
# is the order on the CAN bus and in the encoder.
SENSOR_ANGLES_MRAD: tuple[int, ...] = (0, 785, 1571, 2356, 3142, -2356, -1571, -785)
SENSOR_COUNT = len(SENSOR_ANGLES_MRAD)
SENSOR_FOV_MRAD = 262  # ~15 deg cone per sensor (a fan of rays in the sim)
# Each sensor sits on the body's rim at its angle; a reading is the distance
# from there to the nearest obstacle in its cone, which the twin and the sim
# sample with SENSOR_FAN_RAYS rays spread evenly over SENSOR_FOV_MRAD.
SENSOR_MOUNT_RADIUS_MM = ROBOT_RADIUS_MM
SENSOR_FAN_RAYS = 3
RANGE_MIN_MM = 20
RANGE_MAX_MM = 2000

# Reading status: the values of DroneCAN's uavcan.equipment.range_sensor.Measurement
# reading_type (UNDEFINED, VALID_RANGE, TOO_CLOSE, TOO_FAR), so a DroneCAN rangefinder's
# reading passes through unchanged; an all-zero frame reads as invalid.
RANGE_INVALID = 0
RANGE_VALID = 1
RANGE_TOO_CLOSE = 2
RANGE_TOO_FAR = 3

# --- actions ----------------------------------------------------------------
# (left, right) wheel speed in mm/s for each discrete action of the sector
# encoding, held for one control period.
ACTION_NAMES: tuple[str, ...] = ("forward", "turn_left", "turn_right", "reverse")
ACTION_WHEEL_SPEEDS_MM_S: tuple[tuple[int, int], ...] = (
    (400, 400),
    (-160, 160),
    (160, -160),
    (-200, -200),
)
# The cell encoding's grid actions (the paper's up/down/left/right), as world
# directions; the controller executes them as motion primitives.
CELL_ACTION_NAMES: tuple[str, ...] = ("up", "down", "left", "right")
CELL_ACTION_DELTAS: tuple[tuple[int, int], ...] = ((0, -1), (0, 1), (-1, 0), (1, 0))  # (dcol, drow)

GOAL_TOLERANCE_MM = 150  # goal counts as reached inside this distance
DEFAULT_CELL_SIZE_MM = 500


def cell_center_mm(col: int, row: int, height: int, cell_mm: int = DEFAULT_CELL_SIZE_MM) -> tuple[int, int]:
    """World position (mm) of a map cell's centre; see the module docstring."""
    return (col * cell_mm + cell_mm // 2, (height - row) * cell_mm - cell_mm // 2)


def world_to_cell(x_mm: int, y_mm: int, height: int, cell_mm: int = DEFAULT_CELL_SIZE_MM) -> tuple[int, int]:
    """Map cell (col, row) containing a world point (mm)."""
    return (x_mm // cell_mm, height - 1 - (y_mm // cell_mm))
