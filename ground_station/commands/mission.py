"""`qnav mission upload --targets A,B,C,D | FILE` and `qnav mission download`.

Upload: waypoints from map targets (their cell centres in world metres,
`--map`, default paper10) or from a QGC WPL 110 file (as written by
MAVProxy, QGroundControl or `mission download --out`), sent through the
MAVLink mission protocol; waits for MISSION_ACK and exits 3 with the robot's
reason on refusal, 4 on timeout. Target waypoints travel in
MAV_FRAME_LOCAL_NED (x north, y east) so they are exact.

Download: prints the robot's mission (world metres, x east / y north) and
with `--out FILE` writes it as QGC WPL 110.
"""

from __future__ import annotations

import argparse


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.mavlink.link import add_link_args

    p = sub.add_parser("mission", help="upload or download the robot's mission (MAVLink)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    verbs = p.add_subparsers(dest="verb", metavar="VERB")
    verbs.required = True
    up = verbs.add_parser("upload", help="upload waypoints (map targets or a WPL file)")
    up.add_argument("file", nargs="?", metavar="FILE", help="QGC WPL 110 waypoint file")
    up.add_argument("--targets", metavar="A,B,...", help="map target names, in visiting order")
    up.add_argument("--map", default="paper10", metavar="NAME|PATH", help="map of the targets (default paper10)")
    up.add_argument("--cell-size", type=float, default=None, metavar="M",
                    help="cell size in metres (default: the map's, 0.5)")
    down = verbs.add_parser("download", help="print the robot's mission")
    down.add_argument("--out", metavar="FILE", help="also write it as a QGC WPL 110 file")
    for v in (up, down):
        add_link_args(v)
        v.set_defaults(func=run)


def target_items(targets: str, map_name: str, cell_size_m: float | None = None) -> list[tuple[int, int, int]]:
    """(frame, x, y) MISSION_ITEM_INT items (LOCAL_NED, metres * 1e4) for map targets."""
    from firmware_py import robot_spec
    from ground_station.errors import CliError
    from ground_station.maps import MapError, load_map
    from ground_station.mavlink.link import mavlink

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
    from ground_station.errors import CliError
    from ground_station.mavlink.link import mavutil

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


def run(args: argparse.Namespace) -> int:
    from ground_station.errors import CliError
    from ground_station.mavlink.link import run_on_link

    if args.verb == "upload":
        if bool(args.targets) == bool(args.file):
            raise CliError("give either --targets A,B,... or a waypoint FILE")
        items = target_items(args.targets, args.map, args.cell_size) if args.targets else file_items(args.file)

        def upload(link) -> int:
            n = link.mission_upload(items)
            print(f"mission of {n} waypoints accepted")
            return 0

        return run_on_link(args, "mission upload", upload)

    def download(link) -> int:
        items = link.mission_download()
        m = link.m
        print(f"{len(items)} items")
        for it in items:
            if it.frame == m.MAV_FRAME_LOCAL_NED:
                print(f"{it.seq:3d} local  x={it.y / 1e4:.3f} m east  y={it.x / 1e4:.3f} m north")
            else:
                print(f"{it.seq:3d} global lat={it.x / 1e7:.7f} lon={it.y / 1e7:.7f} (frame {it.frame})")
        if args.out:
            _write_wpl(args.out, items)
        return 0

    return run_on_link(args, "mission download", download)


def _write_wpl(path: str, items: list) -> None:
    """QGC WPL 110 (float x/y: metres for local frames, degrees for global)."""
    from firmware_py.atomic import atomic_write
    from ground_station.mavlink.link import mavlink

    m = mavlink()
    lines = ["QGC WPL 110"]
    for it in items:
        scale = 1e4 if it.frame == m.MAV_FRAME_LOCAL_NED else 1e7
        lines.append("\t".join(str(v) for v in (
            it.seq, it.current, it.frame, it.command, it.param1, it.param2, it.param3, it.param4,
            f"{it.x / scale:.7f}", f"{it.y / scale:.7f}", f"{it.z:g}", it.autocontinue)))
    atomic_write(path, "\n".join(lines) + "\n", make_parents=True)
