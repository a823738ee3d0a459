"""Mission items for `Link.mission_upload` and from `Link.mission_download`:
waypoints from map targets (their cell centres, LOCAL_NED, exact) or from a
QGC WPL 110 file, and a downloaded mission written back as QGC WPL 110.
Bad input raises `CliError` with one line naming what is wrong."""

from __future__ import annotations

from ground_station.errors import CliError
from ground_station.mavlink.link import mavlink, mavutil


def target_items(targets: str, map_name: str, cell_size_m: float | None = None) -> list[tuple[int, int, int]]:
    """(frame, x, y) MISSION_ITEM_INT items (LOCAL_NED, metres * 1e4) for map targets."""
    from firmware_py import robot_spec
    from ground_station.maps import MapError, load_map

    try:
        gm = load_map(map_name) if cell_size_m is None else load_map(map_name, cell_size_m)
    except (MapError, OSError) as exc:
        raise CliError(str(exc)) from exc
    cell_mm = round(gm.cell_size_m * 1000)
    names = [t.strip() for t in targets.split(",") if t.strip()]
    if not names:
        raise CliError("--targets is empty")
    items = []
    for name in names:
        if name not in gm.targets:
            raise CliError(f"map {gm.name} has no target {name!r} (has {', '.join(sorted(gm.targets))})")
        col, row = gm.targets[name]
        x_mm, y_mm = robot_spec.cell_center_mm(col, row, gm.height, cell_mm)
        items.append((mavlink().MAV_FRAME_LOCAL_NED, y_mm * 10, x_mm * 10))  # north, east in m * 1e4
    return items


def file_items(path: str) -> list[tuple[int, int, int]]:
    """NAV_WAYPOINT items of a QGC WPL file, as MISSION_ITEM_INT (frame, x, y)."""

    m = mavutil().mavlink  # MAVLINK20 set before mavwp pulls in pymavlink
    from pymavlink import mavwp
    loader = mavwp.MAVWPLoader()
    try:
        loader.load(path)
    except Exception as exc:  # mavwp raises bare Exceptions with its own text
        raise CliError(f"cannot read waypoint file {path}: {exc}") from exc
    items = []
    for i in range(loader.count()):
        w = loader.wp(i)
        if w.command != m.MAV_CMD_NAV_WAYPOINT:
            raise CliError(f"{path}: item {i} is command {w.command}, only NAV_WAYPOINT (16) is supported")
        scale = 1e4 if w.frame == m.MAV_FRAME_LOCAL_NED else 1e7
        x, y = (w.x, w.y) if w.get_type() == "MISSION_ITEM_INT" else (round(w.x * scale), round(w.y * scale))
        items.append((w.frame, x, y))
    if not items:
        raise CliError(f"{path}: no waypoints")
    return items


def write_wpl(path: str, items: list) -> None:
    """QGC WPL 110 (float x/y: metres for local frames, degrees for global)."""
    from firmware_py.atomic import atomic_write

    m = mavlink()
    lines = ["QGC WPL 110"]
    for it in items:
        scale = 1e4 if it.frame == m.MAV_FRAME_LOCAL_NED else 1e7
        lines.append("\t".join(str(v) for v in (
            it.seq, it.current, it.frame, it.command, it.param1, it.param2, it.param3, it.param4,
            f"{it.x / scale:.7f}", f"{it.y / scale:.7f}", f"{it.z:g}", it.autocontinue)))
    atomic_write(path, "\n".join(lines) + "\n", make_parents=True)
