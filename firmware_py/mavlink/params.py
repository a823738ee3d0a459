"""The robot's MAVLink parameter table and its persistence.

Owns the list of parameters (name <= 16 chars, type, default, range, description), which
`VehicleConfig` field or node setting each one drives, range enforcement, and the JSON file in the
storage directory that keeps them across reboots (replaced atomically; a corrupt or unreadable file
means defaults plus a warning, never a crash). Every parameter is an INT32 carried as a float32, the
robot storing the exact integer: docs/mavlink.md, "Parameters".
"""

from __future__ import annotations

import json
import logging
import os
import struct
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Protocol

from firmware_py import robot_spec
from firmware_py.atomic import atomic_write
from firmware_py.vehicle import FailsafeAction, VehicleConfig

log = logging.getLogger("qnav.params")

PARAM_FILE = "params/params.json"  # storage layout: firmware_py.storage.PARAMS_FILE
FILE_VERSION = 1

MAV_PARAM_TYPE_INT32 = 6  # MAVLink MAV_PARAM_TYPE_INT32 (ArduPilot style: value cast to float)


class DeferredSaver(Protocol):
    """Where `ParamStore` hands its saves when one is attached (a storage worker)."""

    def submit(self, key: str, job: Callable[[], None]) -> bool: ...
    def flush(self, timeout_s: float = 5.0) -> bool: ...


@dataclass(frozen=True)
class ParamDef:
    """One parameter: `field` names the VehicleConfig field it drives (None
    for node settings); read-only ones mirror the vehicle's status."""

    name: str
    default: int
    min: int
    max: int
    description: str
    field: str | None = None
    readonly: bool = False
    reboot_required: bool = False
    local: bool = False  # settable on the robot only (params file, command line), never by PARAM_SET


_CFG = VehicleConfig()

PARAMS: tuple[ParamDef, ...] = (
    # --- node ---------------------------------------------------------------
    ParamDef("SYSID_THISMAV", 1, 1, 254, "MAVLink system id of the robot (applied at reboot)",
             reboot_required=True),
    ParamDef("MAV_COMPID", 1, 1, 254, "MAVLink component id of the robot (applied at reboot)",
             reboot_required=True),
    ParamDef("SIGN_REQUIRE", 1, 0, 1,
             "1: with a signing key set, drop unsigned/badly signed input (RADIO_STATUS excepted); "
             "0: accept unsigned input too (outgoing still signed)"),
    ParamDef("SIGN_NET_SETUP", 0, 0, 1,
             "1: accept an unsigned SETUP_SIGNING over a network link while no key is set; 0: only "
             "over a serial link or with --signing-key (set on the robot only: params.json)", local=True),
    ParamDef("SYSID_MYGCS", 255, 0, 255,
             "system id of the GCS that may control the robot (sticks, RC override, modes, arming, goals, "
             "missions, PARAM_SET) and whose heartbeats keep the GCS failsafe alive, as ArduPilot's (255: "
             "QGroundControl, Mission Planner, MAVProxy and qnav; 0: any system may control, and the "
             "failsafe follows the first GCS heard after boot, which a router's own heartbeat can be)"),
    ParamDef("TELEM_POS_HZ", 5, 0, 50,
             "default rate of LOCAL_POSITION_NED, ATTITUDE, GLOBAL_POSITION_INT (0 = off)"),
    ParamDef("TELEM_NAV_HZ", 2, 0, 50,
             "default rate of NAV_CONTROLLER_OUTPUT, OBSTACLE_DISTANCE, MISSION_CURRENT, "
             "NAMED_VALUE_INT, POSITION_TARGET_LOCAL_NED (0 = off)"),
    ParamDef("MIS_TIMEOUT_MS", 1500, 100, 10_000,
             "mission transfer: wait for the next item this long before re-requesting it"),
    ParamDef("MIS_RETRIES", 3, 0, 10, "mission transfer: re-requests before the upload is cancelled"),
    ParamDef("FS_GCS_ENABLE", 1, 0, 1,
             "1: GCS failsafe armed once a GCS heartbeat has been seen; 0: off"),
    # --- controller (VehicleConfig) -----------------------------------------
    ParamDef("CTRL_RATE_HZ", _CFG.control_rate_hz, robot_spec.CONTROL_RATE_MIN_HZ, robot_spec.CONTROL_RATE_MAX_HZ,
             "control loop rate (the active policy's control period must match)", "control_rate_hz"),
    ParamDef("SENS_TIMEOUT_MS", _CFG.sensor_timeout_ms, 20, 5000,
             "sensor data older than this -> stop and FAULT", "sensor_timeout_ms"),
    ParamDef("MOT_TIMEOUT_MS", _CFG.motor_timeout_ms, 20, 2000,
             "motor driver watchdog timeout", "motor_timeout_ms"),
    ParamDef("MAX_WHEEL_SPD", _CFG.max_wheel_speed_mm_s, 10, robot_spec.MAX_WHEEL_SPEED_MM_S,
             "wheel speed limit (mm/s)", "max_wheel_speed_mm_s"),
    ParamDef("SPEED_SCALE", _CFG.speed_scale_pct, 10, 100,
             "scale of the action table's wheel speeds (%)", "speed_scale_pct"),
    ParamDef("GOAL_TOL_MM", _CFG.goal_tolerance_mm, 20, 2000,
             "goal counts as reached inside this distance (mm)", "goal_tolerance_mm"),
    ParamDef("FS_GCS_TOUT_MS", _CFG.gcs_timeout_ms, 500, 120_000,
             "no GCS heartbeat for this long -> GCS failsafe (robot clock, ms)", "gcs_timeout_ms"),
    ParamDef("FS_GCS_ACTION", int(_CFG.gcs_failsafe_action), 0, 2,
             "GCS failsafe action: 0 none (report only), 1 Hold, 2 disarm", "gcs_failsafe_action"),
    # the geodetic origin = home: the world's (0, 0) on the Earth, sent as GPS_GLOBAL_ORIGIN and
    # HOME_POSITION; global mission items and goals are converted around it (docs/mavlink.md, Frames)
    ParamDef("ORIGIN_LAT", _CFG.origin_lat_e7, -900_000_000, 900_000_000,
             "latitude of the world origin and home (1e-7 deg)", "origin_lat_e7"),
    ParamDef("ORIGIN_LON", _CFG.origin_lon_e7, -1_800_000_000, 1_800_000_000,
             "longitude of the world origin and home (1e-7 deg)", "origin_lon_e7"),
    ParamDef("ORIGIN_ALT_MM", _CFG.origin_alt_mm, -1_000_000, 10_000_000,
             "altitude AMSL of the world origin and home (mm)", "origin_alt_mm"),
    ParamDef("CELL_SIZE_MM", _CFG.cell_size_mm, 50, 5000, "map cell size (mm)", "cell_size_mm"),
    ParamDef("CM_STOP_MM", _CFG.collision_stop_mm, 0, 1000,
             "collision monitor: no straight motion toward a range reading nearer than this in the "
             "robot's path (mm; turning stays allowed; 0 = off)", "collision_stop_mm"),
    ParamDef("CM_SLOW_MM", _CFG.collision_slow_mm, 0, 2000,
             "collision monitor: straight motion at CM_SLOW_PCT toward a reading nearer than this (mm; 0 = off)",
             "collision_slow_mm"),
    ParamDef("CM_SLOW_PCT", _CFG.collision_slow_pct, 0, 100,
             "collision monitor: speed in the slow zone (% of the command)", "collision_slow_pct"),
    ParamDef("NAV_STALL_S", _CFG.nav_stall_s, 0, 600,
             "a drive that neither gets closer to its goal nor moves for this long (s, robot clock) is "
             "reported (STATUSTEXT with the reason) and held (0 = off)", "nav_stall_s"),
    # --- read-only mirrors of the vehicle status ------------------------------
    ParamDef("POLICY_ID", 0, 0, 2**32 - 1,
             "id of the active policy (read-only; float32 on the wire, exact in the two 16-bit halves below)",
             readonly=True),
    ParamDef("POLICY_ID_HI", 0, 0, 0xFFFF, "upper 16 bits of POLICY_ID (read-only)", readonly=True),
    ParamDef("POLICY_ID_LO", 0, 0, 0xFFFF, "lower 16 bits of POLICY_ID (read-only)", readonly=True),
    ParamDef("POLICY_CRC", 0, 0, 2**32 - 1,
             "CRC32 of the active policy file (read-only; float32 on the wire, exact in the "
             "two 16-bit halves below)", readonly=True),
    ParamDef("POLICY_CRC_HI", 0, 0, 0xFFFF, "upper 16 bits of POLICY_CRC (read-only)", readonly=True),
    ParamDef("POLICY_CRC_LO", 0, 0, 0xFFFF, "lower 16 bits of POLICY_CRC (read-only)", readonly=True),
)

assert all(len(p.name) <= 16 for p in PARAMS)
assert {p.field for p in PARAMS if p.field} == {f.name for f in fields(VehicleConfig)}
assert FailsafeAction.DISARM.value == 2


def as_float32(value: int) -> float:
    """The value a PARAM_VALUE carries for an integer (C cast to float32)."""
    wire: float = struct.unpack("<f", struct.pack("<f", float(value)))[0]
    return wire


class ParamStore:
    """Parameter values, range-checked, persisted in `<storage>/params.json`.

    `storage_dir=None` keeps the table in memory only (tests, no storage).
    """

    def __init__(self, storage_dir: str | os.PathLike[str] | None = None) -> None:
        self._defs = {p.name: p for p in PARAMS}
        self._order = [p.name for p in PARAMS]
        self._values = {p.name: p.default for p in PARAMS}
        self.path = Path(storage_dir) / PARAM_FILE if storage_dir is not None else None
        # a storage worker (firmware_py.mavlink.link_thread.StorageWorker): saves run there,
        # coalesced, instead of in the caller's thread; load() flushes it first
        self.deferred: DeferredSaver | None = None
        self.save_errors = 0  # saves that failed (disk full, read-only storage)
        self._save_failure: str | None = None  # the newest failure not yet reported to the GCS

    # --- table ----------------------------------------------------------------
    def names(self) -> list[str]:
        return list(self._order)

    def unknown(self, name: str) -> str:
        """The refusal for a name not in the table, with the closest one if any is close."""
        import difflib

        near = difflib.get_close_matches(str(name).upper(), self._order, n=1, cutoff=0.75)
        return f"unknown parameter {name}" + (f" (did you mean {near[0]}?)" if near else "")

    def index(self, name: str) -> int:
        return self._order.index(name)

    def definition(self, name: str) -> ParamDef:
        return self._defs[name]

    def __contains__(self, name: str) -> bool:
        return name in self._defs

    def __len__(self) -> int:
        return len(self._order)

    def get(self, name: str) -> int:
        return self._values[name]

    def set(self, name: str, value: float,
            check: Callable[[VehicleConfig], tuple[bool, str]] | None = None, *,
            remote: bool = False) -> tuple[bool, str]:
        """Set from a MAVLink PARAM_SET value. On refusal the stored value is unchanged and the
        reason says why. Persists on success. `check` (the vehicle's `check_config`) judges the config a
        controller parameter would make before anything is stored. `remote`: the value came over
        MAVLink (robot-local parameters are refused then)."""
        d = self._defs.get(name)
        if d is None:
            return False, self.unknown(name)
        if d.readonly:
            return False, f"{name} is read-only"
        if remote and d.local:
            return False, f"{name} can only be set on the robot (params.json)"
        if (not isinstance(value, (int, float)) or isinstance(value, bool) or value != value
                or value in (float("inf"), float("-inf"))):
            return False, f"{name}: not a number"
        ivalue = round(value)
        # float32 cannot hold every int > 2**24 exactly: accept the float32 image of an int
        if abs(value - ivalue) > max(1e-6, abs(value) * 1.2e-7):
            return False, f"{name} must be an integer, got {value:g}"
        if not d.min <= ivalue <= d.max:
            return False, f"{name}={ivalue} out of range [{d.min}, {d.max}]"
        if check is not None and d.field is not None and ivalue != self._values[name]:
            ok, why = check(replace(self.vehicle_config(), **{d.field: ivalue}))
            if not ok:
                return False, f"{name}={ivalue}: {why}"
        if ivalue != self._values[name]:
            self._values[name] = ivalue
            if self.deferred is not None:
                self.deferred.submit("params", self.save)
            else:
                self.save()
        return True, ""

    def set_readonly(self, name: str, value: int) -> None:
        """Update a read-only mirror (POLICY_ID, ...) from the vehicle status."""
        assert self._defs[name].readonly
        self._values[name] = int(value)

    def update_policy(self, policy_id: int, policy_crc: int) -> None:
        for name, value in (("POLICY_ID", policy_id), ("POLICY_CRC", policy_crc)):
            self.set_readonly(name, value & 0xFFFFFFFF)
            self.set_readonly(name + "_HI", (value >> 16) & 0xFFFF)
            self.set_readonly(name + "_LO", value & 0xFFFF)

    def vehicle_config(self) -> VehicleConfig:
        return VehicleConfig(**{p.field: self._values[p.name] for p in PARAMS if p.field})

    # --- persistence ------------------------------------------------------------
    def save(self) -> None:
        """Write the table (atomically). A failure is kept for `pop_save_failure`
        (the node reports it to the GCS: the echoed values are not stored) and
        never raises: the values stay in effect until a reboot."""
        if self.path is None:
            return
        values = {p.name: self._values[p.name] for p in PARAMS if not p.readonly}
        text = json.dumps({"version": FILE_VERSION, "params": values}, indent=1, sort_keys=True)
        try:
            atomic_write(self.path, text + "\n", make_parents=True)
        except OSError as exc:
            self.save_errors += 1
            self._save_failure = f"params not saved ({exc.strerror or exc}): lost at reboot"
            log.error("parameter save failed: %s", exc)
        else:
            self._save_failure = None

    def pop_save_failure(self) -> str | None:
        """The newest save failure since the last call (None: none, or a later save succeeded)."""
        out, self._save_failure = self._save_failure, None
        return out

    def load(self) -> list[str]:
        """Reset to defaults, then apply the stored file. Returns warnings
        (one line each) for anything ignored; never raises on bad content."""
        if self.deferred is not None:
            self.deferred.flush()  # a save still queued would be read back as the old table
        self._values.update({p.name: p.default for p in PARAMS if not p.readonly})
        if self.path is None or not self.path.exists():
            return []
        try:
            doc = json.loads(self.path.read_text())
            if not isinstance(doc, dict) or doc.get("version") != FILE_VERSION:
                raise ValueError(f"unsupported version {doc.get('version') if isinstance(doc, dict) else doc!r}")
            stored = doc["params"]
            if not isinstance(stored, dict):
                raise ValueError("'params' is not an object")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            return [f"params file corrupt ({exc}); using defaults"]
        warnings = []
        for name, value in stored.items():
            d = self._defs.get(name)
            if d is None or d.readonly:
                warnings.append(f"params file: ignored unknown {name}")
            elif not isinstance(value, int) or isinstance(value, bool) or not d.min <= value <= d.max:
                warnings.append(f"params file: {name}={value!r} invalid; default {d.default}")
            else:
                self._values[name] = value
        return warnings
