"""Component metadata (MAVLink's Component Metadata microservice): what a ground station needs to
show the robot's parameters with descriptions, units, ranges and defaults.

Two JSON files in the robot's storage, written at boot from the parameter table
(`firmware_py.mavlink.params.PARAMS`, the one owner of every name, range and text) and served
read-only by its FTP server:

* `/metadata/parameters.json`: the parameter metadata (QGroundControl's parameter schema:
  name, type, shortDesc, units, default, min, max, rebootRequired, readOnly, group);
* `/metadata/general.json`: the general metadata (vendor, model, firmware version and the
  `metadataTypes` list pointing at the parameter file by `mftp://` URI with its CRC).

COMPONENT_METADATA (on `MAV_CMD_REQUEST_MESSAGE` 397) carries the general file's URI and CRC
(the CRC32 the FTP server's CalcFileCRC32 reports for it). Units come from the parameter's name,
as its suffix says them (`_MM` mm, `_MS` ms, `_HZ` Hz, `_PCT` %; ArduPilot names its parameters
the same way).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from firmware_py.atomic import atomic_write

METADATA_DIR = "/metadata"
GENERAL_FILE = "/metadata/general.json"
PARAMETER_FILE = "/metadata/parameters.json"
COMP_METADATA_TYPE_PARAMETER = 1  # MAVLink COMP_METADATA_TYPE
_UNITS = (("_MM", "mm"), ("_MS", "ms"), ("_HZ", "Hz"), ("_PCT", "%"), ("_US", "us"), ("_SPD", "mm/s"))


def uri(ftp_path: str) -> str:
    """The MAVLink FTP URI of a file on this component's FTP server."""
    return "mftp://" + ftp_path


def units_of(name: str) -> str:
    return next((u for suffix, u in _UNITS if name.endswith(suffix)), "")


def parameter_metadata() -> dict[str, Any]:
    from firmware_py.mavlink.params import PARAMS

    params = []
    for p in PARAMS:
        entry: dict[str, Any] = {"name": p.name, "type": "Int32",  # PARAM_VALUE: MAV_PARAM_TYPE_INT32, C-cast
                                 "shortDesc": p.description, "default": p.default, "min": p.min,
                                 "max": p.max, "rebootRequired": bool(p.reboot_required),
                                 "readOnly": bool(p.readonly), "group": "controller" if p.field else "node"}
        if units_of(p.name):
            entry["units"] = units_of(p.name)
        params.append(entry)
    return {"version": 1, "scope": "Firmware", "parameters": params}


def general_metadata(param_crc: int, sw_version: int) -> dict[str, Any]:
    """`sw_version`: AUTOPILOT_VERSION's flight_sw_version (major, minor, patch in its top bytes)."""
    return {"version": 1, "vendorName": "qnav", "modelName": "qnav-robot (tabular Q-learning ground robot)",
            "firmwareVersion": f"{sw_version >> 24}.{(sw_version >> 16) & 0xFF}.{(sw_version >> 8) & 0xFF}",
            "metadataTypes": [{"type": COMP_METADATA_TYPE_PARAMETER, "uri": uri(PARAMETER_FILE),
                               "fileCrc": param_crc}]}


def write_metadata(storage_dir: Path, sw_version: int) -> tuple[int, str]:
    """Write both files under `storage_dir`; (the general file's CRC32, "") or (0, why not)."""
    from firmware_py.storage import Storage

    try:
        params = json.dumps(parameter_metadata(), indent=1).encode()
        root = Path(storage_dir)
        atomic_write(root / PARAMETER_FILE.lstrip("/"), params, make_parents=True)
        storage = Storage(root)
        general = json.dumps(general_metadata(storage.crc32(PARAMETER_FILE), sw_version), indent=1).encode()
        atomic_write(root / GENERAL_FILE.lstrip("/"), general, make_parents=True)
        return storage.crc32(GENERAL_FILE), ""
    except OSError as exc:
        return 0, f"component metadata not written: {exc}"
