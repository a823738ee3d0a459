"""Mission items for `Link.mission_upload` and from `Link.mission_download`: waypoints from map
targets (their cell centres, made in LOCAL_NED, exact; `Link.use_global_frame` has the link send
them as lat/lon around the robot's origin) or from a QGC WPL 110 file, and a downloaded mission
written back as QGC WPL 110. Bad input raises `CliError` with one line naming what is wrong."""

from __future__ import annotations

import argparse

from firmware_py import robot_spec
from firmware_py.mavlink.frames import LOCAL_ITEM_SCALE
from ground_station.errors import CliError
from ground_station.mavlink.link import finite_float, mavlink, mavutil


def parse_start(text: str) -> tuple[float, float]:
    """`--start X,Y` (world metres, x east, y north) -> (x_mm, y_mm); CliError
    naming the option unless both are finite numbers."""
    try:
        x, y = (finite_float(v) for v in text.split(","))
    except (ValueError, argparse.ArgumentTypeError):  # ValueError: not two values
        raise CliError(f"--start must be X,Y in metres (finite numbers), got {text!r}") from None
    return x * 1000.0, y * 1000.0


def load_gridmap(map_name: str, cell_size_m: float | None = None):
    """The map (`ground_station.maps.load_map`), CliError with its reason if it cannot be read."""
    from ground_station.maps import MapError, load_map

    try:
        return load_map(map_name) if cell_size_m is None else load_map(map_name, cell_size_m)
    except (MapError, OSError) as exc:
        raise CliError(str(exc)) from None


def goal_cell(gridmap, x_m: float, y_m: float) -> tuple[int, int]:
    """The map cell of world point (x_m, y_m); CliError unless it is a free cell."""
    cell_mm = round(gridmap.cell_size_m * 1000)
    col, row = robot_spec.world_to_cell(round(x_m * 1000), round(y_m * 1000), gridmap.height, cell_mm)
    if not gridmap.in_bounds(col, row) or not gridmap.is_free(col, row):
        raise CliError(f"goal ({x_m:g}, {y_m:g}) m is not in a free cell of map {gridmap.name}")
    return col, row


PROFILE_HELP = ("--plan: the robot's profile (docs/robot-profile.md): segments keep its body radius "
                "clear (default: the built-in robot's 150 mm)")


def add_profile_arg(parser: argparse.ArgumentParser) -> None:
    """`--profile FILE.toml` of the commands that plan (`qnav mission upload --plan`, `qnav goal --plan`)."""
    parser.add_argument("--profile", metavar="FILE.toml", help=PROFILE_HELP)


def profile_radius_arg(args: argparse.Namespace) -> float | None:
    """The body radius (mm) of `--profile FILE.toml` (None without one), read before any link;
    CliError in one line if it is given without --plan or does not load."""
    if not args.profile:
        return None
    if not args.plan:
        raise CliError("--profile needs --plan")
    from ground_station.maps.planner import profile_radius_mm

    try:
        return profile_radius_mm(args.profile)
    except ValueError as exc:
        raise CliError(f"--profile {exc}") from None


def body_text(radius_mm: float | None) -> str:
    """" for a 180 mm body" (empty for the planner's default body)."""
    return "" if radius_mm is None else f" for a {radius_mm:g} mm body"


def planned_goal_items(gridmap, x_m: float, y_m: float, start_mm: tuple[float, float],
                       radius_mm: float | None = None) -> list[tuple[int, int, int]]:
    """`qnav goal --plan`: the planner's waypoints from `start_mm` to the goal's cell
    (`planned_items`) for a body of `radius_mm` (None: the built-in robot's), the last
    one moved from the cell's centre to the goal itself."""
    kw = None if radius_mm is None else {"radius_mm": radius_mm}
    items, _ = planned_items([goal_cell(gridmap, x_m, y_m)], start_mm, gridmap, kw)
    items[-1] = (mavlink().MAV_FRAME_LOCAL_NED, round(y_m * LOCAL_ITEM_SCALE), round(x_m * LOCAL_ITEM_SCALE))
    return items


def target_items(targets: str, gm) -> list[tuple[int, int, int]]:
    """(frame, x, y) MISSION_ITEM_INT items (LOCAL_NED, metres * LOCAL_ITEM_SCALE) for the targets of map `gm`."""
    cell_mm = round(gm.cell_size_m * 1000)
    items = []
    for col, row in target_cells(targets, gm):
        x_mm, y_mm = robot_spec.cell_center_mm(col, row, gm.height, cell_mm)
        items.append((mavlink().MAV_FRAME_LOCAL_NED, y_mm * LOCAL_ITEM_SCALE // 1000, x_mm * LOCAL_ITEM_SCALE // 1000))  # north, east
    return items


def _check_wpl_lines(path: str) -> None:
    """One line naming the first malformed line of a QGC WPL file (pymavlink's
    loader says only e.g. "could not convert string to float: 'abc'")."""
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            lines = f.read().splitlines()
    except OSError as exc:
        raise CliError(f"cannot read waypoint file {path}: {exc.strerror or exc}") from None
    if not lines or not lines[0].startswith("QGC WPL"):
        raise CliError(f"{path}:1: not a QGC WPL file (first line {lines[0][:30]!r})" if lines
                       else f"{path}: empty file")
    for n, line in enumerate(lines[1:], 2):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != 12:
            raise CliError(f"{path}:{n}: {len(fields)} fields, a QGC WPL 110 item has 12")
        for k, v in enumerate(fields):
            try:
                float(v)
            except ValueError:
                raise CliError(f"{path}:{n}: field {k + 1} {v!r} is not a number") from None


def file_items(path: str) -> list[tuple[int, int, int]]:
    """NAV_WAYPOINT items of a QGC WPL file, as MISSION_ITEM_INT (frame, x, y)."""
    m = mavutil().mavlink  # MAVLINK20 set before mavwp pulls in pymavlink
    from pymavlink import mavwp
    _check_wpl_lines(path)
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
        scale = LOCAL_ITEM_SCALE if w.frame == m.MAV_FRAME_LOCAL_NED else 1e7
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
        scale = LOCAL_ITEM_SCALE if it.frame == m.MAV_FRAME_LOCAL_NED else 1e7
        lines.append("\t".join(str(v) for v in (
            it.seq, it.current, it.frame, it.command, it.param1, it.param2, it.param3, it.param4,
            f"{it.x / scale:.7f}", f"{it.y / scale:.7f}", f"{it.z:g}", it.autocontinue)))
    atomic_write(path, "\n".join(lines) + "\n", make_parents=True)


def planned_items(targets: list[tuple[int, int]], start_mm: tuple[float, float], gridmap,
                  plan_kw: dict | None = None) -> tuple[list[tuple[int, int, int]], list[int]]:
    """The ground station's planned waypoints (`ground_station.maps.planner`) from `start_mm`
    through the target cells in order, as LOCAL_NED mission items, and the item index of each
    target (the last waypoint of its leg). A sector policy steers to the current item's bearing,
    so it needs these intermediate waypoints; a cell policy does not. CliError if a leg cannot be
    planned."""
    from ground_station.maps import MapError
    from ground_station.maps.planner import plan_waypoints

    items: list[tuple[int, int, int]] = []
    target_seq: list[int] = []
    frame = mavlink().MAV_FRAME_LOCAL_NED
    start: tuple = tuple(start_mm)
    from_mm = True
    for cell in targets:
        try:
            wps = plan_waypoints(gridmap, start, cell, start_mm=from_mm, **(plan_kw or {}))
        except MapError as exc:
            raise CliError(f"cannot plan to {cell}: {exc}") from None
        items += [(frame, round(y * LOCAL_ITEM_SCALE / 1000), round(x * LOCAL_ITEM_SCALE / 1000)) for x, y in wps]  # N, E
        target_seq.append(len(items) - 1)
        start, from_mm = cell, False
    return items, target_seq


def target_cells(targets: str, gridmap) -> list[tuple[int, int]]:
    """The cells of comma-separated target names on gridmap (CliError on an unknown one)."""
    names = [t.strip() for t in targets.split(",") if t.strip()]
    if not names:
        raise CliError("--targets is empty")
    for name in names:
        if name not in gridmap.targets:
            raise CliError(f"map {gridmap.name} has no target {name!r} (has {', '.join(sorted(gridmap.targets))})")
    return [gridmap.targets[n] for n in names]


def robot_position_mm(link, timeout_s: float = 3.0) -> tuple[float, float]:
    """The robot's world position (x east, y north, mm) from its LOCAL_POSITION_NED
    telemetry; CliError if none arrives within timeout_s."""
    msg = link.recv("LOCAL_POSITION_NED", timeout_s)
    if msg is None:
        raise CliError(f"--plan: no LOCAL_POSITION_NED from the robot within {timeout_s:g} s "
                       "(give the start with --start X,Y)")
    return msg.y * 1000.0, msg.x * 1000.0  # east, north
