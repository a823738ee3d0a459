"""The robot profile: what this robot is built from, read from a TOML file.

`qnav-robot --profile FILE` (and `qnav-sim --profile FILE`, which plays the same robot) takes the
robot's geometry and the backends that talk to its drive and its range sensors from here; without a
file the robot is the one `robot_spec` describes, on qnav's own CAN frames. Layout and every key:
docs/robot-profile.md; an example per backend ships in `firmware_py/profiles/`.

`load_profile` checks every key (type, range, unknown names) and raises `ProfileError` with one line
naming the file and the key. What a policy needs of the robot is checked against the profile in
`firmware_py.needs`. Stdlib only (tomllib).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from firmware_py import robot_spec
from firmware_py.layout import MAX_SENSORS, MIN_SENSORS, Layout

DRIVE_BACKENDS = ("qnav", "odrive", "dronecan")
SENSOR_BACKENDS = ("qnav", "dronecan")
DRONECAN_COMMANDS = ("rpm", "raw")


class ProfileError(ValueError):
    """A robot profile that cannot be used; the text is one line naming the file and the key."""


# The file's sections and keys; what each key means: the table in docs/robot-profile.md
@dataclass(frozen=True)
class Geometry:
    wheel_base_mm: int = robot_spec.WHEEL_BASE_MM
    wheel_radius_mm: int = robot_spec.WHEEL_RADIUS_MM
    robot_radius_mm: int = robot_spec.ROBOT_RADIUS_MM
    encoder_counts_per_rev: int = robot_spec.ENCODER_TICKS_PER_REV


@dataclass(frozen=True)
class DriveConfig:
    backend: str = "qnav"
    left_node: int = 0
    right_node: int = 1
    left_sign: int = 1
    right_sign: int = 1
    max_speed_mm_s: int = robot_spec.MAX_WHEEL_SPEED_MM_S
    gear_ratio: float = 1.0
    command: str = "rpm"
    max_rpm: int = 0


@dataclass(frozen=True)
class SensorConfig:
    backend: str = "qnav"
    angles_deg: tuple[float, ...] = (0.0, 45.0, 90.0, 135.0, 180.0, -135.0, -90.0, -45.0)
    max_range_mm: int = robot_spec.RANGE_MAX_MM
    max_ranges_mm: tuple[int, ...] = ()
    sensor_ids: tuple[int, ...] = tuple(range(robot_spec.SENSOR_COUNT))

    def ranges_mm(self) -> tuple[int, ...]:
        """Each sensor's maximum range."""
        return self.max_ranges_mm or (self.max_range_mm,) * len(self.angles_deg)


@dataclass(frozen=True)
class BoardsConfig:
    bumper: bool = True
    power: bool = False


@dataclass(frozen=True)
class DroneCanConfig:
    node_id: int = 100
    node_name: str = "org.qnav.robot"


@dataclass(frozen=True)
class RobotProfile:
    geometry: Geometry = field(default_factory=Geometry)
    drive: DriveConfig = field(default_factory=DriveConfig)
    sensors: SensorConfig = field(default_factory=SensorConfig)
    boards: BoardsConfig = field(default_factory=BoardsConfig)
    dronecan: DroneCanConfig = field(default_factory=DroneCanConfig)
    source: str = "built-in default"

    def wheel_circumference_mm(self) -> float:
        return 2 * math.pi * self.geometry.wheel_radius_mm

    def layout(self) -> Layout:
        """The geometry and sensor layout the controller's parts take (firmware_py.layout)."""
        g = self.geometry
        return Layout(robot_radius_mm=g.robot_radius_mm, wheel_base_mm=g.wheel_base_mm,
                      wheel_radius_mm=g.wheel_radius_mm, counts_per_rev=g.encoder_counts_per_rev,
                      max_wheel_speed_mm_s=self.drive.max_speed_mm_s,
                      angles_mrad=tuple(round(a * math.pi / 180 * 1000) for a in self.sensors.angles_deg),
                      max_ranges_mm=self.sensors.ranges_mm(), bumper=self.boards.bumper)


DEFAULT = RobotProfile()
assert DEFAULT.layout() == Layout()  # the built-in robot is the default profile

_SECTIONS: dict[str, type] = {"geometry": Geometry, "drive": DriveConfig, "sensors": SensorConfig,
                              "boards": BoardsConfig, "dronecan": DroneCanConfig}


def _check(where: str, cond: bool, why: str) -> None:
    if not cond:
        raise ProfileError(f"{where}: {why}")


def _value(where: str, default: Any, value: Any) -> Any:
    """`value` converted to the field's type, or ProfileError."""
    if isinstance(default, bool):
        _check(where, isinstance(value, bool), f"expected true or false, got {value!r}")
        return value
    if isinstance(default, int):
        _check(where, isinstance(value, int) and not isinstance(value, bool), f"expected an integer, got {value!r}")
        return value
    if isinstance(default, float):
        _check(where, isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value),
               f"expected a number, got {value!r}")
        return float(value)
    if isinstance(default, str):
        _check(where, isinstance(value, str), f"expected a string, got {value!r}")
        return value
    if isinstance(default, tuple):
        _check(where, isinstance(value, list) and len(value) > 0, f"expected a non-empty list, got {value!r}")
        item = default[0] if default else 0
        return tuple(_value(f"{where}[{i}]", item, v) for i, v in enumerate(value))
    raise AssertionError(f"unhandled field type at {where}")


def profile_from_dict(data: dict[str, Any], source: str) -> RobotProfile:
    """A checked profile from parsed TOML (`source` names the file in errors)."""
    parts: dict[str, Any] = {}
    for section, value in data.items():
        where = f"{source}: [{section}]"
        _check(where, section in _SECTIONS, f"unknown section (expected {', '.join(_SECTIONS)})")
        _check(where, isinstance(value, dict), "expected a table")
        cls = _SECTIONS[section]
        defaults = cls()
        known = {f.name for f in fields(cls)}
        kw = {}
        for key, v in value.items():
            kwhere = f"{source}: {section}.{key}"
            _check(kwhere, key in known, f"unknown key (expected one of {', '.join(sorted(known))})")
            kw[key] = _value(kwhere, getattr(defaults, key), v)
        if section == "sensors" and "angles_deg" in kw and "sensor_ids" not in kw:
            kw["sensor_ids"] = tuple(range(len(kw["angles_deg"])))  # one id per sensor, in order
        parts[section] = cls(**kw)
    prof = RobotProfile(**parts, source=source)
    _validate(prof, source)
    return prof


def _validate(p: RobotProfile, src: str) -> None:
    g, d, s, dc = p.geometry, p.drive, p.sensors, p.dronecan
    for key in ("wheel_base_mm", "wheel_radius_mm", "robot_radius_mm", "encoder_counts_per_rev"):
        v = getattr(g, key)
        _check(f"{src}: geometry.{key}", 0 < v <= 100_000, f"expected 1..100000, got {v}")
    _check(f"{src}: drive.backend", d.backend in DRIVE_BACKENDS,
           f"expected one of {', '.join(DRIVE_BACKENDS)}, got {d.backend!r}")
    _check(f"{src}: sensors.backend", s.backend in SENSOR_BACKENDS,
           f"expected one of {', '.join(SENSOR_BACKENDS)}, got {s.backend!r}")
    node_max = 31 if d.backend == "odrive" else 19 if d.backend == "dronecan" else 63
    for key in ("left_node", "right_node"):
        v = getattr(d, key)
        _check(f"{src}: drive.{key}", 0 <= v <= node_max,
               f"expected 0..{node_max} for the {d.backend} backend, got {v}")
    _check(f"{src}: drive.right_node", d.left_node != d.right_node, f"the same as left_node ({d.left_node})")
    for key in ("left_sign", "right_sign"):
        _check(f"{src}: drive.{key}", getattr(d, key) in (1, -1), f"expected 1 or -1, got {getattr(d, key)}")
    _check(f"{src}: drive.max_speed_mm_s", 0 < d.max_speed_mm_s <= robot_spec.MAX_WHEEL_SPEED_MM_S,
           f"expected 1..{robot_spec.MAX_WHEEL_SPEED_MM_S}, got {d.max_speed_mm_s}")
    _check(f"{src}: drive.gear_ratio", 0.01 <= d.gear_ratio <= 1000, f"expected 0.01..1000, got {d.gear_ratio}")
    _check(f"{src}: drive.command", d.command in DRONECAN_COMMANDS,
           f"expected one of {', '.join(DRONECAN_COMMANDS)}, got {d.command!r}")
    _check(f"{src}: drive.max_rpm", 0 <= d.max_rpm <= 100_000, f"expected 0..100000, got {d.max_rpm}")
    _check(f"{src}: sensors.angles_deg", all(-180 <= a <= 180 for a in s.angles_deg),
           "every angle in -180..180 degrees")
    _check(f"{src}: sensors.max_range_mm", 0 < s.max_range_mm <= 4095, f"expected 1..4095, got {s.max_range_mm}")
    n = len(s.angles_deg)
    _check(f"{src}: sensors.angles_deg", MIN_SENSORS <= n <= MAX_SENSORS,
           f"{n} sensors; expected {MIN_SENSORS}..{MAX_SENSORS}")
    # qnav's own RangeSectors0/1 frames carry exactly 8 sectors (qnav.dbc); DroneCAN Measurements any count
    _check(f"{src}: sensors.angles_deg", s.backend != "qnav" or n == robot_spec.SENSOR_COUNT,
           f"{n} sensors; qnav's RangeSectors frames carry exactly {robot_spec.SENSOR_COUNT} "
           "(another count needs sensors.backend = \"dronecan\")")
    _check(f"{src}: sensors.max_ranges_mm", not s.max_ranges_mm or len(s.max_ranges_mm) == n,
           f"{len(s.max_ranges_mm)} ranges for {n} sensors")
    _check(f"{src}: sensors.max_ranges_mm", all(0 < r <= 4095 for r in s.max_ranges_mm), "every range in 1..4095 mm")
    _check(f"{src}: sensors.sensor_ids", len(s.sensor_ids) == len(s.angles_deg),
           f"{len(s.sensor_ids)} ids for {len(s.angles_deg)} angles")
    _check(f"{src}: sensors.sensor_ids", len(set(s.sensor_ids)) == len(s.sensor_ids)
           and all(0 <= i <= 255 for i in s.sensor_ids), "expected distinct ids in 0..255")
    _check(f"{src}: dronecan.node_id", 1 <= dc.node_id <= 125, f"expected 1..125, got {dc.node_id}")
    _check(f"{src}: dronecan.node_name", 0 < len(dc.node_name) <= 80 and dc.node_name.isascii(),
           "expected 1..80 ASCII characters")


def load_profile(path: str | Path) -> RobotProfile:
    """Read and check a profile file; ProfileError (one line, naming file and key) otherwise."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ProfileError(f"{p}: cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ProfileError(f"{p}: not UTF-8 text") from None
    except tomllib.TOMLDecodeError as exc:
        raise ProfileError(f"{p}: not valid TOML: {exc}") from None
    except RecursionError:  # tomllib recurses once a nesting level
        raise ProfileError(f"{p}: arrays or inline tables nested too deeply") from None
    return profile_from_dict(data, str(p))
