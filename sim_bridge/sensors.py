"""Simulated range sensors, wheel encoders and bumper ring.

Everything a robot profile says about them is the profile's (`firmware_py.profile`; the default is
the built-in robot of `robot_spec`):

Range sensors: one per entry of the profile's `sensors.angles_deg`, in that (bus) order and count,
each a fan of rays spread over robot_spec.SENSOR_FOV_MRAD (no profile key: every sensor has that
cone), cast with pymunk's `segment_query_first` and a ShapeFilter that excludes the robot. Rays
start at the robot's centre (never inside a wall, unlike the rim when touching one) and the reading
is the nearest hit minus the body radius: the distance from the sensor face on the rim. Seeded
Gaussian noise and dropout; readings below RANGE_MIN_MM or beyond the profile's
`sensors.max_range_mm` are flagged as DroneCAN does. Angles are taken in whole milliradians, as the
robot records them (`RobotProfile.layout`).

Encoders integrate each wheel's ground speed (from the body's motion) into ticks at the profile's
`encoder_counts_per_rev` of a wheel of its `wheel_radius_mm`, with an optional per-wheel scale error
(measured / true travel) and seeded slip (each physics step's travel times 1 + N(0, slip)). Named
combinations: sim_bridge/profiles.py. The bumper reads the contacts kept by the world's collision
handlers.

Every random draw comes from one seeded `random.Random` in a fixed order, so a run is reproducible
from its seed.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass

import pymunk

from firmware_py import can_protocol as cp
from firmware_py import robot_spec
from firmware_py.profile import DEFAULT as DEFAULT_ROBOT
from firmware_py.profile import SensorConfig
from sim_bridge.world import ROBOT_CATEGORY, World


@dataclass(frozen=True)
class RangeParams:
    fan_rays: int = 3
    noise_std_mm: float = 10.0
    dropout: float = 0.0  # probability that a reading is INVALID

    def __post_init__(self) -> None:
        if self.fan_rays < 1:
            raise ValueError(f"fan needs at least one ray, got {self.fan_rays}")
        if not 0.0 <= self.dropout <= 1.0:
            raise ValueError(f"dropout must be in [0, 1], got {self.dropout}")
        if self.noise_std_mm < 0:
            raise ValueError(f"noise must be >= 0, got {self.noise_std_mm}")


def sensor_angles_mrad(sensors: SensorConfig) -> list[int]:
    """The profile's sensor directions in whole milliradians, in bus order (the built-in
    robot's are robot_spec.SENSOR_ANGLES_MRAD)."""
    return [round(math.radians(a) * 1000) for a in sensors.angles_deg]


class RangeSensors:
    """The profile's range sensors on the robot's rim (the built-in robot's eight by default)."""

    def __init__(self, world: World, params: RangeParams, rng: random.Random,
                 sensors: SensorConfig = DEFAULT_ROBOT.sensors) -> None:
        self.world = world
        self.p = params
        self.rng = rng
        self.filter = pymunk.ShapeFilter(mask=pymunk.ShapeFilter.ALL_MASKS() ^ ROBOT_CATEGORY)
        fov = robot_spec.SENSOR_FOV_MRAD / 1000
        n = params.fan_rays
        offsets = [0.0] if n == 1 else [-fov / 2 + fov * j / (n - 1) for j in range(n)]
        self.angles_mrad = sensor_angles_mrad(sensors)
        self.directions = [[a / 1000 + o for o in offsets] for a in self.angles_mrad]
        self.max_range_mm = sensors.max_range_mm
        self.reach_m = world.radius_m + self.max_range_mm / 1000 + 0.05
        self.last_rays: list[tuple[tuple[float, float], tuple[float, float], int]] = []
        self._geometry: list[tuple[tuple[float, float], tuple[float, float]]] = []

    def true_ranges_mm(self) -> list[float | None]:
        """Noise-free distance from the rim to the nearest obstacle per sector (None: nothing in reach)."""
        x, y = self.world.body.position
        heading = self.world.body.angle
        radius_mm = self.world.radius_m * 1000
        query = self.world.space.segment_query_first
        reach = self.reach_m
        out: list[float | None] = []
        rays = []
        for fan in self.directions:
            best: float | None = None
            best_end: tuple[float, float] = (x, y)  # set with best, or below when nothing is hit
            for d in fan:
                a = heading + d
                end = (x + reach * math.cos(a), y + reach * math.sin(a))
                hit = query((x, y), end, 0.0, self.filter)
                if hit is not None and (best is None or hit.alpha < best):
                    best, best_end = hit.alpha, hit.point
            if best is None:
                out.append(None)
                a = heading + fan[len(fan) // 2]
                best_end = (x + reach * math.cos(a), y + reach * math.sin(a))
            else:
                out.append(best * reach * 1000 - radius_mm)
            rays.append(((x, y), (best_end[0], best_end[1])))
        self._geometry = rays
        return out

    def read(self) -> list[tuple[int, int]]:
        """(mm, status) per sensor, as on the bus."""
        readings = []
        rays = []
        true = self.true_ranges_mm()
        for dist, ray in zip(true, self._geometry, strict=True):
            drop = self.rng.random() < self.p.dropout
            noise = self.rng.gauss(0.0, self.p.noise_std_mm) if self.p.noise_std_mm > 0 else 0.0
            if drop:
                reading = (0, robot_spec.RANGE_INVALID)
            elif dist is None or dist + noise > self.max_range_mm:
                reading = (self.max_range_mm, robot_spec.RANGE_TOO_FAR)
            elif dist + noise < robot_spec.RANGE_MIN_MM:
                reading = (robot_spec.RANGE_MIN_MM, robot_spec.RANGE_TOO_CLOSE)
            else:
                reading = (round(dist + noise), robot_spec.RANGE_VALID)
            readings.append(reading)
            rays.append((ray[0], ray[1], reading[1]))
        self.last_rays = rays
        return readings


class WheelEncoders:
    """Cumulative tick counts of both wheels (the profile's wheel and counts per turn: the world's geometry)."""

    def __init__(self, world: World, rng: random.Random, slip_std: float = 0.0,
                 scale: tuple[float, float] = (1.0, 1.0)) -> None:
        if slip_std < 0:
            raise ValueError(f"slip must be >= 0, got {slip_std}")
        if not all(s > 0 for s in scale):
            raise ValueError(f"encoder scale must be > 0, got {scale}")
        self.world = world
        self.rng = rng
        self.slip_std = slip_std
        self.scale = scale  # (left, right): measured / true travel (a worn or different wheel)
        g = world.geometry
        self.counts_per_rev = g.encoder_counts_per_rev
        self.ticks_per_m = g.encoder_counts_per_rev / (2 * math.pi * g.wheel_radius_mm / 1000)
        self.ticks = [0.0, 0.0]

    def integrate(self, dt_s: float) -> None:
        left, right = self.world.wheel_ground_speeds()
        if self.slip_std > 0:
            left *= 1.0 + self.rng.gauss(0.0, self.slip_std)
            right *= 1.0 + self.rng.gauss(0.0, self.slip_std)
        self.ticks[0] += left * dt_s * self.ticks_per_m * self.scale[0]
        self.ticks[1] += right * dt_s * self.ticks_per_m * self.scale[1]

    def wheel_turns(self) -> tuple[float, float]:
        """Each wheel's measured turns since the start (unwrapped, fractional): what an ODrive's
        encoder estimate is made of."""
        return self.ticks[0] / self.counts_per_rev, self.ticks[1] / self.counts_per_rev

    def counts(self) -> tuple[int, int]:
        """Counts as on the bus (two's complement of the frame's width, wrapping)."""
        return cp.wrap_counts(math.floor(self.ticks[0])), cp.wrap_counts(math.floor(self.ticks[1]))


_ANGLE = cp.DB.get_message_by_name("Bumper").get_signal_by_name("Bump_AngleMrad")
assert _ANGLE.minimum is not None and _ANGLE.maximum is not None, "qnav.dbc: Bump_AngleMrad has no range"
_ANGLE_MIN_MRAD, _ANGLE_MAX_MRAD = int(_ANGLE.minimum), int(_ANGLE.maximum)


def bumper_signals(world: World, counter: int = 0) -> dict[str, int]:
    """Bumper frame signals from the world's current contacts; `counter` is the sample counter."""
    heading = world.body.angle
    zones = {"Bump_Front": 0, "Bump_Left": 0, "Bump_Rear": 0, "Bump_Right": 0}
    for angle in world.contacts.values():
        rel = _wrap_pi(angle - heading)
        if abs(rel) <= math.pi / 4:
            zones["Bump_Front"] = 1
        elif math.pi / 4 < rel < 3 * math.pi / 4:
            zones["Bump_Left"] = 1
        elif -3 * math.pi / 4 < rel < -math.pi / 4:
            zones["Bump_Right"] = 1
        else:
            zones["Bump_Rear"] = 1
    rel_last = round(_wrap_pi(world.last_contact_angle - heading) * 1000)
    return {"Bump_Pressed": int(bool(world.contacts)), **zones,
            "Bump_Events": world.contact_events % 256,
            "Bump_AngleMrad": max(_ANGLE_MIN_MRAD, min(_ANGLE_MAX_MRAD, rel_last)),
            "Bump_Counter": counter % cp.SENSOR_COUNTER_MODULUS}


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi
