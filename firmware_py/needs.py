"""What a policy needs of the robot: recorded in its `.qtab` by the exporter (`robot_needs` metadata),
checked by the robot against its profile at boot and on upload, printed by `qnav policy inspect`.
Stdlib only.

A policy is trained for one robot (`TrainedFor`: a robot profile as the trainer's twin played it,
`qnav train --profile`; the built-in robot without one); what of it the policy's behaviour depends
on is per kind (`PolicyKind.needs`), and that is all the robot checks. The table per kind, and how
a file without a record (or with the older `robot_geometry` one) is read: docs/robot-profile.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from firmware_py import robot_spec
from firmware_py.layout import Layout

NEEDS_KEY = "robot_needs"
LEGACY_KEY = "robot_geometry"
ANGLE_TOL_MRAD = 175  # 10 degrees: a sector read from a sensor this far from where the twin read it
BASE_TOL = 0.10  # a wheel base within 10 % of the trained one (the turn actions' rate within 10 %)
ACTION_SPEED_MM_S = max(max(abs(lw), abs(rw)) for lw, rw in robot_spec.ACTION_WHEEL_SPEEDS_MM_S)


def wheel_speed(max_speed_mm_s: int) -> int:
    """The fastest wheel speed a policy's actions drive at on a robot clamped to `max_speed_mm_s`."""
    return min(ACTION_SPEED_MM_S, max_speed_mm_s)


def sector_deg(k: int) -> int:
    """Policy sector k's direction in whole degrees (0, 45, ..., -45)."""
    return round(math.degrees(robot_spec.SENSOR_ANGLES_MRAD[k] / 1000.0))


@dataclass(frozen=True)
class TrainedFor:
    """The robot a policy was trained for, as the twin played it: body radius, wheel base, the wheel
    speed its actions drive at, and each of the policy's eight sectors' angle and reach as the robot
    reads it (None / 0: no sensor covers it, read as INVALID)."""

    wheel_base_mm: int = robot_spec.WHEEL_BASE_MM
    robot_radius_mm: int = robot_spec.ROBOT_RADIUS_MM
    wheel_speed_mm_s: int = ACTION_SPEED_MM_S
    sector_angles_mrad: tuple[int | None, ...] = robot_spec.SENSOR_ANGLES_MRAD
    sector_ranges_mm: tuple[int, ...] = (robot_spec.RANGE_MAX_MM,) * robot_spec.SENSOR_COUNT
    source: str = "built-in default"

    @classmethod
    def of_layout(cls, lay: Layout, source: str) -> TrainedFor:
        sl = lay.sector_layout()
        return cls(wheel_base_mm=lay.wheel_base_mm, robot_radius_mm=lay.robot_radius_mm,
                   wheel_speed_mm_s=wheel_speed(lay.max_wheel_speed_mm_s),
                   sector_angles_mrad=tuple(None if j is None else sl.angles_mrad[k]
                                            for k, j in enumerate(lay.sector_of)),
                   sector_ranges_mm=tuple(0 if j is None else sl.max_ranges_mm[k] for k, j in enumerate(lay.sector_of)),
                   source=source)

    @classmethod
    def of_profile(cls, profile: Any) -> TrainedFor:
        """A `firmware_py.profile.RobotProfile` (None: the built-in robot)."""
        if profile is None:
            return cls()
        return cls.of_layout(profile.layout(), _file_name(profile.source))

    @classmethod
    def of_legacy(cls, rec: dict[str, Any]) -> TrainedFor:
        """The older `robot_geometry` record (wheel base, body radius, sensor angles, one max range)."""
        d = cls()
        angles = tuple(int(a) for a in rec.get("sensor_angles_mrad", robot_spec.SENSOR_ANGLES_MRAD))
        rng = int(rec.get("max_range_mm", robot_spec.RANGE_MAX_MM))
        lay = Layout(robot_radius_mm=int(rec.get("robot_radius_mm", d.robot_radius_mm)),
                     wheel_base_mm=int(rec.get("wheel_base_mm", d.wheel_base_mm)), angles_mrad=angles,
                     max_ranges_mm=(rng,) * len(angles))
        return cls.of_layout(lay, "robot_geometry record")

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "wheel_base_mm": self.wheel_base_mm, "robot_radius_mm": self.robot_radius_mm,
                "wheel_speed_mm_s": self.wheel_speed_mm_s, "sector_angles_mrad": list(self.sector_angles_mrad),
                "sector_ranges_mm": list(self.sector_ranges_mm)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainedFor:
        """From `to_dict` (a run's meta.json `robot`); ValueError (one line) if malformed."""
        try:
            angles = tuple(None if a is None else int(a) for a in d["sector_angles_mrad"])
            ranges = tuple(int(r) for r in d["sector_ranges_mm"])
            out = cls(wheel_base_mm=int(d["wheel_base_mm"]), robot_radius_mm=int(d["robot_radius_mm"]),
                      wheel_speed_mm_s=int(d["wheel_speed_mm_s"]), sector_angles_mrad=angles,
                      sector_ranges_mm=ranges, source=str(d.get("source", "")))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"robot record: {exc!r}") from None
        if len(angles) != robot_spec.SENSOR_COUNT or len(ranges) != robot_spec.SENSOR_COUNT:
            raise ValueError(f"robot record: {len(angles)} sector angles, {len(ranges)} ranges "
                             f"(expected {robot_spec.SENSOR_COUNT})")
        return out


def _file_name(source: str) -> str:
    """A profile's source as recorded: its file name (the path is the training machine's)."""
    return source.replace("\\", "/").rsplit("/", 1)[-1]


DEFAULT = TrainedFor()


def sector_needs(trained: TrainedFor, sectors: tuple[int, ...], range_mm: int) -> list[dict[str, Any]]:
    """The `sectors` entries of a need: each sector read, the angle the twin read it at, the range
    the encoder tells apart."""
    return [{"sector_deg": sector_deg(k), "angle_mrad": trained.sector_angles_mrad[k], "range_mm": int(range_mm)}
            for k in sectors]


def policy_needs(kind: Any, encoder: Any, trained: TrainedFor, control_period_us: int) -> dict[str, Any]:
    """The record a policy of `kind` (a `firmware_py.kinds.base.PolicyKind`) with `encoder`, trained
    for `trained`, carries: the common needs and its kind's (`kind.needs`)."""
    out: dict[str, Any] = {"kind": kind.name, "trained_for": trained.source, "control_period_us": int(control_period_us),
                           "wheel_speed_mm_s": trained.wheel_speed_mm_s}
    out.update(kind.needs(encoder, trained))
    return out


def needs_of(policy: Any) -> dict[str, Any]:
    """A loaded policy's need: its record, else one worked out from its `robot_geometry` record or
    (no record) the built-in robot."""
    from firmware_py import kinds

    meta = policy.metadata if isinstance(policy.metadata, dict) else {}
    rec = meta.get(NEEDS_KEY)
    if isinstance(rec, dict):
        return rec
    legacy = meta.get(LEGACY_KEY)
    trained = TrainedFor.of_legacy(legacy) if isinstance(legacy, dict) else DEFAULT
    return policy_needs(kinds.of_policy(policy), policy.encoder, trained, policy.control_period_us)


def needs_mismatch(needs: dict[str, Any], profile: Any) -> str:
    """Why a policy with `needs` must not run on the robot `profile` (a RobotProfile; None: the
    built-in robot), naming both values ('' if it may)."""
    from firmware_py.profile import DEFAULT as DEFAULT_PROFILE

    prof = profile if profile is not None else DEFAULT_PROFILE
    src = prof.source
    lay = prof.layout()
    try:
        want = int(needs.get("wheel_speed_mm_s", ACTION_SPEED_MM_S))
        have = wheel_speed(prof.drive.max_speed_mm_s)
        if want != have:
            return (f"policy trained for wheel speed {want} mm/s, robot profile {src} drives {have} mm/s "
                    f"(drive.max_speed_mm_s {prof.drive.max_speed_mm_s})")
        sl = lay.sector_layout()
        for s in needs.get("sectors", ()):
            deg = int(s["sector_deg"])
            k = next((i for i in range(robot_spec.SENSOR_COUNT) if sector_deg(i) == deg), None)
            if k is None:
                return f"policy reads a sector at {deg} deg, not one of the robot's {robot_spec.SENSOR_COUNT}"
            if lay.sector_of[k] is None:
                return (f"policy reads sector {deg} deg, robot profile {src} has no sensor within 22.5 deg of it "
                        f"(sensors at {', '.join(_deg(a) for a in lay.angles_mrad)} deg)")
            at = s.get("angle_mrad")
            if at is not None and abs(_ang_diff(int(at), sl.angles_mrad[k])) > ANGLE_TOL_MRAD:
                return (f"policy trained with sector {deg} deg read at {_deg(int(at))} deg, robot profile {src} "
                        f"reads it at {_deg(sl.angles_mrad[k])} deg (more than 10 deg apart)")
            if sl.max_ranges_mm[k] < int(s.get("range_mm", 0)):
                return (f"policy reads sector {deg} deg to {int(s['range_mm'])} mm, robot profile {src}'s sensor "
                        f"there reaches {sl.max_ranges_mm[k]} mm")
        rmax = needs.get("robot_radius_mm_max")
        if rmax is not None and lay.robot_radius_mm > int(rmax):
            return (f"policy trained for robot_radius_mm {int(rmax)} at most, robot profile {src} has "
                    f"{lay.robot_radius_mm}")
        base = needs.get("wheel_base_mm")
        if base is not None:
            lo, hi = int(base[0]), int(base[1])
            if not lo <= lay.wheel_base_mm <= hi:
                return (f"policy trained for wheel_base_mm {lo}..{hi}, robot profile {src} has {lay.wheel_base_mm}")
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        return f"policy's {NEEDS_KEY} record is malformed ({exc!r})"
    return ""


def base_window(wheel_base_mm: int) -> list[int]:
    """The wheel bases a policy trained at `wheel_base_mm` runs on (BASE_TOL either way)."""
    return [math.ceil(wheel_base_mm * (1 - BASE_TOL)), math.floor(wheel_base_mm * (1 + BASE_TOL))]


def describe(needs: dict[str, Any]) -> list[str]:
    """`qnav policy inspect`'s lines for a need."""
    lines = [f"trained for: {needs.get('trained_for', '?')}",
             f"control period: {needs.get('control_period_us')} us, wheel speed: {needs.get('wheel_speed_mm_s')} mm/s"]
    for s in needs.get("sectors", ()):
        at = s.get("angle_mrad")
        lines.append(f"sector {s['sector_deg']} deg: a sensor within 10 deg of "
                     f"{'?' if at is None else _deg(int(at))} deg reaching {s.get('range_mm', 0)} mm")
    if needs.get("robot_radius_mm_max") is not None:
        lines.append(f"body radius: at most {needs['robot_radius_mm_max']} mm")
    if needs.get("wheel_base_mm") is not None:
        lo, hi = needs["wheel_base_mm"]
        lines.append(f"wheel base: {lo}..{hi} mm")
    return lines


def _deg(mrad: int) -> str:
    return f"{math.degrees(mrad / 1000.0):.0f}"


def _ang_diff(a_mrad: int, b_mrad: int) -> int:
    return round((((a_mrad - b_mrad) / 1000.0 + math.pi) % (2 * math.pi) - math.pi) * 1000)
