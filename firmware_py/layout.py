"""The robot's body and range sensors as the controller's parts use them: one `Layout`, built from the
robot profile (`firmware_py.profile.RobotProfile.layout`) and handed to each part at construction
(odometry, plausibility, the collision monitor, the localiser, the policy kind's planner, telemetry).
The built-in robot (`robot_spec`) is the default layout, `DEFAULT`.

The sensors are taken as the profile lists them: any count (3..16), at any angles (CCW from the
heading, whole milliradians), each with its own maximum range, in the order their readings arrive.
A policy reads the built-in robot's eight sectors (`robot_spec.SENSOR_ANGLES_MRAD`); `sector_of` maps
each of those to the sensor that looks that way (the nearest one within half the sectors' spacing,
`SECTOR_REACH_MRAD`), and a sector no sensor covers is read as INVALID (unknown, never free):
`to_sectors` turns one tick's readings into the policy's eight, and `sector_layout` is the layout of
those eight readings (each at the angle of the sensor behind it) for the kind's own geometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from firmware_py import robot_spec

MIN_SENSORS = 3
MAX_SENSORS = 16
SECTOR_REACH_MRAD = 393  # half the built-in sectors' 45-degree spacing (22.5 degrees)


def _ang_diff(a_mrad: int, b_mrad: int) -> float:
    return abs((a_mrad - b_mrad) / 1000.0 + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True)
class Layout:
    """Body, wheels and range sensors (module docstring); every field defaults to the built-in robot."""

    robot_radius_mm: int = robot_spec.ROBOT_RADIUS_MM
    wheel_base_mm: int = robot_spec.WHEEL_BASE_MM
    wheel_radius_mm: int = robot_spec.WHEEL_RADIUS_MM
    counts_per_rev: int = robot_spec.ENCODER_TICKS_PER_REV
    max_wheel_speed_mm_s: int = robot_spec.MAX_WHEEL_SPEED_MM_S
    angles_mrad: tuple[int, ...] = robot_spec.SENSOR_ANGLES_MRAD
    max_ranges_mm: tuple[int, ...] = (robot_spec.RANGE_MAX_MM,) * robot_spec.SENSOR_COUNT
    fov_mrad: int = robot_spec.SENSOR_FOV_MRAD
    range_min_mm: int = robot_spec.RANGE_MIN_MM
    bumper: bool = True  # a bumper board reports (its input must be fresh to arm and drive)
    sector_of: tuple[int | None, ...] = field(default=(), compare=False)  # worked out in __post_init__

    def __post_init__(self) -> None:
        if len(self.max_ranges_mm) != len(self.angles_mrad):
            raise ValueError(f"{len(self.max_ranges_mm)} max ranges for {len(self.angles_mrad)} sensors")
        sectors: list[int | None] = []
        for a in robot_spec.SENSOR_ANGLES_MRAD:
            j = min(range(len(self.angles_mrad)), key=lambda k: (abs(_ang_diff(self.angles_mrad[k], a)), k))
            sectors.append(j if abs(_ang_diff(self.angles_mrad[j], a)) * 1000 <= SECTOR_REACH_MRAD else None)
        object.__setattr__(self, "sector_of", tuple(sectors))

    @property
    def count(self) -> int:
        return len(self.angles_mrad)

    @property
    def mount_mm(self) -> int:
        """The sensors sit on the body's rim."""
        return self.robot_radius_mm

    @property
    def max_range_mm(self) -> int:
        """The farthest any sensor reads."""
        return max(self.max_ranges_mm)

    def uncovered(self) -> list[int]:
        """The policy sectors (indices of robot_spec.SENSOR_ANGLES_MRAD) no sensor covers."""
        return [k for k, j in enumerate(self.sector_of) if j is None]

    def identity(self) -> bool:
        """The policy's sectors are the sensors, in order (the built-in layout)."""
        return self.sector_of == tuple(range(robot_spec.SENSOR_COUNT)) and self.count == robot_spec.SENSOR_COUNT

    def to_sectors(self, ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...]
                   ) -> tuple[list[int], list[int]]:
        """One tick's readings (sensor order) as the policy's eight sectors; uncovered: INVALID."""
        read = [None if j is None or j >= len(ranges_mm) else j for j in self.sector_of]
        return ([0 if j is None else ranges_mm[j] for j in read],
                [robot_spec.RANGE_INVALID if j is None else status[j] for j in read])

    def sector_layout(self) -> Layout:
        """The layout of the eight sector readings `to_sectors` gives: each at its sensor's angle and
        range (an uncovered sector at its built-in angle; its reading is always INVALID)."""
        if self.identity():
            return self
        angles = tuple(robot_spec.SENSOR_ANGLES_MRAD[k] if j is None else self.angles_mrad[j]
                       for k, j in enumerate(self.sector_of))
        ranges = tuple(self.max_range_mm if j is None else self.max_ranges_mm[j] for j in self.sector_of)
        return replace(self, angles_mrad=angles, max_ranges_mm=ranges)

    def plausible(self, ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...]) -> list[int]:
        """The statuses the controller may use: a VALID reading beyond its sensor's maximum range (a
        broken or forged frame) is INVALID; a sensor without a reading yet is INVALID."""
        out = []
        for i, lim in enumerate(self.max_ranges_mm):
            st = status[i] if i < len(status) else robot_spec.RANGE_INVALID
            if st == robot_spec.RANGE_VALID and ranges_mm[i] > lim:
                st = robot_spec.RANGE_INVALID
            out.append(st)
        return out


DEFAULT = Layout()
