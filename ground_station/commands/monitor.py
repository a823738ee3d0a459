"""`qnav monitor`: live telemetry dashboard, plain status lines, or a replay.

    qnav monitor [--mavlink URL] [--tlog FILE] [--signing-key FILE] [--map NAME|PATH]
    qnav monitor --plain [--duration S]          one status line per second
    qnav monitor --replay FILE.tlog [--speed X]  a recording through the same view
"""

from __future__ import annotations

import argparse
import os
import sys


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("monitor", help="telemetry dashboard (live, --plain, or --replay a .tlog)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    from ground_station.mavlink.link import DEFAULT_TLOG_DIR, DEFAULT_URL

    p.add_argument("--mavlink", metavar="URL", default=None,
                   help=f"pymavlink connection string to the robot (default {DEFAULT_URL})")
    p.add_argument("--tlog", metavar="FILE",
                   help=f"record the session to this .tlog (default: a new file under {DEFAULT_TLOG_DIR}/)")
    p.add_argument("--no-tlog", action="store_true", help="do not record the session")
    p.add_argument("--signing-key", metavar="FILE",
                   help="MAVLink 2 signing key file (32 bytes, 64 hex chars or a passphrase)")
    p.add_argument("--map", metavar="NAME|PATH", default="paper10",
                   help="map drawn under the robot: built-in name, generator spec or .map path "
                        "(default paper10; 'none' for a blank field)")
    p.add_argument("--cell-size", type=float, default=0.5, metavar="M", help="map cell size in metres (default 0.5)")
    p.add_argument("--plain", action="store_true", help="no dashboard: print one status line per second")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S wall seconds (live --plain)")
    p.add_argument("--replay", metavar="FILE.tlog", help="replay a recording instead of a live link")
    p.add_argument("--speed", type=float, default=1.0, metavar="X",
                   help="replay speed factor (default 1; 0 = as fast as possible)")
    p.set_defaults(func=run)


def _load_map(spec: str, cell_size: float):
    from ground_station.errors import CliError

    if spec.lower() == "none":
        return None
    from ground_station.maps import MapError, load_map

    try:
        return load_map(spec, cell_size_m=cell_size)
    except (MapError, OSError) as exc:
        raise CliError(f"--map {spec}: {exc}") from exc


def open_source(args):
    """The message source the flags ask for (ReplaySource or LiveSource)."""
    from ground_station.errors import CliError
    from ground_station.mavlink.link import DEFAULT_URL
    from ground_station.monitor.sources import ReplaySource, open_live

    if args.replay:
        if args.mavlink or args.tlog or args.signing_key:
            raise CliError("--replay reads a recording; it cannot be combined with --mavlink/--tlog/--signing-key")
        if args.duration is not None:
            raise CliError("--duration is for a live link; a replay ends with its recording")
        if args.speed < 0:
            raise CliError(f"--speed must be >= 0, got {args.speed}")
        if not os.path.isfile(args.replay):
            raise CliError(f"no such tlog: {args.replay}")
        return ReplaySource(args.replay, speed=args.speed), f"replay {os.path.basename(args.replay)} x{args.speed:g}"
    if args.tlog and args.no_tlog:
        raise CliError("--tlog and --no-tlog contradict each other")
    url = args.mavlink or DEFAULT_URL
    tlog = False if args.no_tlog else args.tlog
    try:
        source = open_live(url, tlog=tlog, signing_key=args.signing_key)
    except ValueError as exc:  # bad signing key file
        raise CliError(str(exc)) from exc
    except OSError as exc:
        raise CliError(f"cannot open {url}: {exc}") from exc
    if source.link.tlog_path is not None:
        print(f"recording to {source.link.tlog_path}", file=sys.stderr)
    return source, url


def run(args: argparse.Namespace) -> int:
    from ground_station.errors import CliError
    from ground_station.monitor.model import VehicleView

    if args.duration is not None and args.duration <= 0:
        raise CliError(f"--duration must be > 0, got {args.duration}")
    if args.cell_size <= 0:
        raise CliError(f"--cell-size must be > 0, got {args.cell_size}")
    grid_map = None if args.plain else _load_map(args.map, args.cell_size)
    source, label = open_source(args)
    view = VehicleView()
    try:
        if args.plain:
            from ground_station.monitor.sources import run_plain

            run_plain(source, view, sys.stdout, duration=args.duration)
            return 0
        from ground_station.monitor.app import MonitorApp

        MonitorApp(source, grid_map=grid_map, view=view, subtitle=label).run()
        return 0
    finally:
        source.close()
