"""The map the robot drives on, asked from the robot instead of repeated by hand.

`robot_map(link)` reads, with pymavlink's MAVFTP client, the robot's own `/maps/active.map` (what
`qnav map upload` leaves, its targets in `/maps/active.targets.json` while that names the map's
CRC32), else the map its active policy carries, and returns a `GridMap` (with targets where they are
known); when the two maps differ, one line says which is used. `choose_map(link, gm)` is what
commands use: the robot's map when no `--map` is given, the given one when it is the robot's, and
one line naming both when they differ (a mission planned on another map sends the robot into walls).
The rules: docs/mavlink.md, `qnav mission upload`.
"""

from __future__ import annotations

import json
import logging
import sys
import zlib
from typing import Any

from ground_station.errors import CliError
from ground_station.mavlink.link import LinkError

ACTIVE_POLICY = "/policies/active.qtab"
ACTIVE_MAP = "/maps/active.map"  # firmware_py.storage.ACTIVE_MAP
MAP_TARGETS = "/maps/active.targets.json"  # {"map_crc32": .., "name": .., "targets": {"A": [col, row]}}
READ_UP_TO = 16 * 1024 * 1024  # more than the robot's storage quota: the read ends at the file's end


def read_robot_file(link: Any, path: str) -> bytes | None:
    """A file from the robot's FTP server (pymavlink's MAVFTP), None if it has no such file.
    Asked for its CRC first: one round trip says whether it exists, where MAVFTP.read would wait
    out its 5 s idle timeout after the robot's FileNotFound."""
    from ground_station.mavlink.ftp_upload import ftp_session

    session = ftp_session(link)
    if session.remote_crc(path, wait_s=5.0) is None:
        return None
    root = logging.getLogger()
    root.addFilter(_short_read_warning)
    try:
        data = session.client().read(path, READ_UP_TO)
    finally:
        root.removeFilter(_short_read_warning)
    return bytes(data) if data else None


def _short_read_warning(record: logging.LogRecord) -> bool:
    """MAVFTP.read warns when the file is shorter than asked for; here that is the point."""
    return not (record.pathname.endswith("mavftp.py") and str(record.msg).startswith("expected"))


def running_policy_id(link: Any) -> int | None:
    """POLICY_ID_HI/LO: the policy the robot runs (0: none; None: it does not say)."""
    try:
        return (int(link.param_get("POLICY_ID_HI")) << 16) | int(link.param_get("POLICY_ID_LO"))
    except Exception:  # a robot without these parameters (an older qnav, another autopilot)
        return None


def robot_policy(link: Any) -> Any | None:
    """The robot's active policy (firmware_py.policy.Policy) from its storage, None if there is none
    there; CliError when the robot runs another one (started with `qnav-robot --policy FILE`)."""
    from firmware_py.policy import PolicyError, load_policy

    try:
        data = read_robot_file(link, ACTIVE_POLICY)
    except LinkError as exc:  # no FTP server (a robot without storage, another autopilot)
        raise CliError(f"the robot's map cannot be read ({exc}): give --map NAME|PATH") from None
    running = running_policy_id(link)
    if not data:
        if running:
            raise CliError(f"the robot runs policy 0x{running:08x}, which is not in its storage ({ACTIVE_POLICY}; "
                           "started with qnav-robot --policy?): give --map NAME|PATH")
        return None
    try:
        pol = load_policy(bytes(data))
    except PolicyError as exc:
        raise CliError(f"the robot's {ACTIVE_POLICY} does not load here: {exc}") from None
    if running and running != pol.policy_id:  # (0: the robot says it runs none)
        raise CliError(f"the robot runs policy 0x{running:08x}, its {ACTIVE_POLICY} is 0x{pol.policy_id:08x}: "
                       "give --map NAME|PATH")
    return pol


def _describe(gm: Any) -> str:
    return f"{gm.name} ({gm.width}x{gm.height} cells of {gm.cell_size_m:g} m)"


def targets_file(map_text: bytes, name: str, targets: dict[str, tuple[int, int]]) -> bytes:
    """The sidecar `qnav map upload` leaves beside the robot's map: its targets, tied to the map's CRC32."""
    return json.dumps({"map_crc32": zlib.crc32(map_text), "name": name,
                       "targets": {k: list(v) for k, v in targets.items()}}, indent=1).encode()


def _sidecar_targets(link: Any, map_text: bytes) -> tuple[str, dict[str, tuple[int, int]]]:
    """(name, targets) from MAP_TARGETS when it belongs to `map_text`; ("", {}) otherwise."""
    try:
        raw = read_robot_file(link, MAP_TARGETS)
        doc = json.loads(raw) if raw else None
        if not isinstance(doc, dict) or doc.get("map_crc32") != zlib.crc32(map_text):
            return "", {}
        targets = {str(k): (int(v[0]), int(v[1])) for k, v in dict(doc.get("targets") or {}).items()}
        return str(doc.get("name") or ""), targets
    except Exception:  # a stale, foreign or broken sidecar: the map without targets
        return "", {}


def uploaded_map(link: Any) -> Any | None:
    """The robot's own /maps/active.map as a GridMap (None if it has none), with its targets when the
    sidecar of `qnav map upload` belongs to it."""
    from ground_station.maps import MapError
    from ground_station.maps.movingai import parse_map

    try:
        data = read_robot_file(link, ACTIVE_MAP)
    except LinkError:
        return None
    if not data:
        return None
    try:
        cell_mm = int(link.param_get("CELL_SIZE_MM"))
    except Exception:
        cell_mm = 500
    try:
        gm = parse_map(data.decode("utf-8", "replace"), f"the robot's {ACTIVE_MAP}", cell_mm / 1000.0)
    except MapError as exc:
        raise CliError(f"the robot's {ACTIVE_MAP} does not load here: {exc}") from None
    name, targets = _sidecar_targets(link, data)
    free = {k: v for k, v in targets.items()
            if 0 <= v[0] < gm.width and 0 <= v[1] < gm.height and not gm.occ[v[1], v[0]]}
    gm.targets = free
    gm.name = f"{name or 'map'} ({ACTIVE_MAP} on the robot)"
    return gm


def robot_map(link: Any) -> Any | None:
    """The robot's map as a GridMap (see the module docstring); None if it has none."""
    own = uploaded_map(link)
    try:
        carried = policy_map(link)
    except CliError:
        if own is None:
            raise
        carried = None
    if own is None:
        return carried
    if carried is not None and not same_map(own, carried):
        print(f"note: the robot drives on {_describe(own)}, not its policy's map {_describe(carried)}: "
              f"using the robot's", file=sys.stderr)
    elif carried is not None and not own.targets:
        carried.name = f"{carried.name} ({ACTIVE_MAP} on the robot)"
        return carried  # the same grid: the named map's targets
    return own


def policy_map(link: Any) -> Any | None:
    """The map the robot's active policy carries, as a GridMap; None if it carries none."""
    import numpy as np

    from ground_station.maps import GridMap, MapError, load_map

    pol = robot_policy(link)
    if pol is None or pol.map_grid is None:
        return None
    grid = pol.map_grid
    occ = np.array([[grid.occupied(c, r) for c in range(grid.width)] for r in range(grid.height)], dtype=bool)
    cell_m = grid.cell_mm / 1000.0
    name = str(pol.metadata.get("map") or "") if isinstance(pol.metadata, dict) else ""
    if name:
        try:
            named = load_map(name, cell_m)
        except (MapError, OSError, ValueError):
            named = None
        if named is not None and named.occ.shape == occ.shape and bool((named.occ == occ).all()):
            return named
    return GridMap(f"{name or 'map'} of the robot's policy 0x{pol.policy_id:08x}", occ, cell_size_m=cell_m)


def same_map(a: Any, b: Any) -> bool:
    return (a.occ.shape == b.occ.shape and bool((a.occ == b.occ).all())
            and abs(a.cell_size_m - b.cell_size_m) < 1e-9)


def choose_map(link: Any, gm: Any | None) -> Any:
    """The map a command works on: `gm` (the --map the caller loaded, checked before any link) or the
    robot's; CliError naming both if they differ."""
    if gm is None:
        robot = robot_map(link)
        if robot is None:
            raise CliError(f"the robot has no {ACTIVE_MAP} and its active policy carries no map: "
                           "give --map NAME|PATH (or qnav map upload one)")
        return robot
    try:
        robot = robot_map(link)
    except CliError:  # the robot's map cannot be read (it runs a policy not in its storage): trust --map
        return gm
    if robot is not None and not same_map(gm, robot):
        raise CliError(f"--map {_describe(gm)} is not the robot's map {_describe(robot)} "
                       f"(leave out --map to use it)")
    return gm
