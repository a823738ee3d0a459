"""The map the robot drives on, asked from the robot instead of repeated by hand (issue 30 item 4).

The robot's active policy (`/policies/active.qtab` on its FTP server) carries
the map it localises and plans on: its occupancy grid (`map_grid`), the
training map's name (`map`) and geometry. `robot_map(link)` reads it with
pymavlink's own MAVFTP client over the link and returns it as a `GridMap`:
the named map itself (with its targets) when a map of that name or path is
at hand here and has exactly that grid, else the grid alone (no targets).
`choose_map(link, gm)` is what commands use: the robot's map when no
`--map` is given; the given one when it is the robot's; and one line naming
both when they differ (a mission planned on another map sends the robot
into walls).
"""

from __future__ import annotations

import logging
from typing import Any

from ground_station.errors import CliError

ACTIVE_POLICY = "/policies/active.qtab"
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
    from ground_station.mavlink.link import LinkError

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


def robot_map(link: Any) -> Any | None:
    """The robot's map as a GridMap (see the module docstring); None if its policy carries none."""
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
            raise CliError("the robot's active policy carries no map: give --map NAME|PATH")
        return robot
    try:
        robot = robot_map(link)
    except CliError:  # the robot's map cannot be read (it runs a policy not in its storage): trust --map
        return gm
    if robot is not None and not same_map(gm, robot):
        raise CliError(f"--map {_describe(gm)} is not the robot's map {_describe(robot)} "
                       f"(from its active policy; leave out --map to use it)")
    return gm
