"""`qnav log mcap RUN_DIR|FILE.tlog [--tlog FILE] [--can FILE] [--trajectory
FILE] [--map NAME|PATH] [--out FILE.mcap]`: a run as one MCAP file for
Foxglove, PlotJuggler (3.8+) and Rerun. `qnav log list|pull`: the robot's
own log files (its storage's logs/, over MAVLink FTP; docs/deploy.md).

A run folder (`qnav demo`, `qnav sitl`) gives its tlog, CAN log (can.blf),
the sim's trajectory.csv, the robot's robot.log and the map named in its
summary.json; a tlog alone gives the MAVLink topics (add --can /
--trajectory / --map for the rest). A `qnav sitl` folder has no tlog (the
GCS keeps its own): give it with --tlog. Topics, schemas and clocks:
ground_station/logs/topics.py and docs/monitor.md. The file is written
beside the target and renamed over it when complete.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ground_station.commands import add_actions
from ground_station.errors import CliError
from ground_station.mavlink.link import add_link_args, run_on_link


def add_subparser(sub: argparse._SubParsersAction) -> None:
    inner = add_actions(sub, "log", "convert a run's recordings (MCAP for Foxglove, PlotJuggler, Rerun)", __doc__,
                        "log_command")
    m = inner.add_parser("mcap", help="one MCAP file with the whole run", description=__doc__,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    m.add_argument("target", metavar="RUN_DIR|FILE.tlog", help="a run folder or a session tlog")
    m.add_argument("--tlog", metavar="FILE", help="the session tlog (default: the run's *.tlog)")
    m.add_argument("--can", metavar="FILE", help="CAN log (.blf, .asc, candump -L .log; default: the run's can.blf)")
    m.add_argument("--trajectory", metavar="FILE", help="the sim's trajectory.csv (default: the run's)")
    m.add_argument("--map", metavar="NAME|PATH",
                   help="map for the /map grid (default: the run's summary.json map; 'none' for no map)")
    m.add_argument("--out", metavar="FILE.mcap", help="output (default: RUN_DIR/run.mcap, or FILE.mcap beside the tlog)")
    m.set_defaults(func=run_mcap)
    ls = inner.add_parser("list", help="the robot's own log files (logs/ in its storage, over MAVLink FTP)",
                          description="List the robot's onboard log files (firmware_py/onboard_log.py: "
                                      "logs/robot.log and its rotated copies) with their sizes.")
    add_link_args(ls)
    ls.set_defaults(func=run_list)
    pull = inner.add_parser("pull", help="fetch the robot's own log files over MAVLink FTP",
                            description="Fetch the robot's onboard log files (all, or the NAMEs given) into "
                                        "--out; each file is written beside its final name and renamed over it.")
    add_link_args(pull)
    pull.add_argument("names", nargs="*", metavar="NAME", help="files to fetch (default: every file in logs/)")
    pull.add_argument("--out", type=Path, default=Path("robot-logs"), metavar="DIR",
                      help="where to put them (default %(default)s)")
    pull.set_defaults(func=run_pull)


ROBOT_LOG_DIR = "/logs"  # firmware_py.onboard_log.LOG_DIR under the robot's storage root


def plain_name_problem(name: str) -> str | None:
    """Why `name` (from the robot's listing or the command line) is not a plain file name to write
    inside --out (no '../x' or absolute name escapes it), or None."""
    import os

    if name in ("", ".", ".."):
        return "not a file name"
    seps = {"/", "\\", os.sep, os.altsep or "/"}
    if any(c in name for c in seps) or "\0" in name:
        return "has a path separator or NUL: only a plain file name is written into --out"
    return None


def _robot_logs(link) -> list[tuple[str, int]]:
    from ground_station.mavlink.ftp_upload import ftp_session

    listing = ftp_session(link).list_dir(ROBOT_LOG_DIR)
    if listing is None:
        raise CliError(f"the robot has no {ROBOT_LOG_DIR} (started without --storage, or an older qnav-robot)")
    return sorted((name, size) for name, size in listing if size is not None and size >= 0)


def run_list(args: argparse.Namespace) -> int:
    def body(link) -> int:
        files = _robot_logs(link)
        for name, size in files:
            print(f"{size:>10}  {ROBOT_LOG_DIR}/{name}")
        print(f"{len(files)} file(s), {sum(s for _, s in files)} bytes")
        return 0

    return run_on_link(args, "log list", body)


def run_pull(args: argparse.Namespace) -> int:
    from firmware_py.atomic import atomic_write
    from ground_station.mavlink.robot_map import read_robot_file

    def body(link) -> int:
        files = dict(_robot_logs(link))
        names = args.names or sorted(files)
        for name in names:  # every name checked before anything is written
            why = plain_name_problem(name)
            if why:
                where = "given" if args.names else f"in the robot's {ROBOT_LOG_DIR} listing"
                raise CliError(f"log name {name!r} ({where}) refused: {why}")
        missing = [n for n in names if n not in files]
        if missing:
            raise CliError(f"no {ROBOT_LOG_DIR}/{missing[0]} on the robot (it has {', '.join(sorted(files)) or 'none'})")
        args.out.mkdir(parents=True, exist_ok=True)
        for name in names:
            data = read_robot_file(link, f"{ROBOT_LOG_DIR}/{name}") if files[name] else b""
            if data is None:
                raise CliError(f"{ROBOT_LOG_DIR}/{name} went away while fetching (rotated?): pull again")
            atomic_write(args.out / name, data)
            print(f"{args.out / name}: {len(data)} bytes")
        return 0

    return run_on_link(args, "log pull", body)


def run_mcap(args: argparse.Namespace) -> int:
    from ground_station.logs.mcap_run import McapError, find_run_files, write_run_mcap
    from ground_station.maps import MapError, load_map

    target = Path(args.target)
    try:
        tlog, can_log, trajectory, map_name = find_run_files(target)
    except McapError as exc:
        raise CliError(str(exc)) from None
    tlog = Path(args.tlog) if args.tlog else tlog
    can_log = Path(args.can) if args.can else can_log
    trajectory = Path(args.trajectory) if args.trajectory else trajectory
    for what, path in (("--tlog", tlog), ("--can", can_log), ("--trajectory", trajectory)):
        if path is not None and not path.is_file():
            raise CliError(f"{what} {path}: no such file")
    map_name = args.map or map_name
    grid_map = None
    if map_name and map_name != "none":
        try:
            grid_map = load_map(map_name)
        except (MapError, OSError) as exc:
            raise CliError(f"--map {map_name}: {exc}") from None
    out = Path(args.out) if args.out else (target / "run.mcap" if target.is_dir() else target.with_suffix(".mcap"))
    robot_log = target / "robot.log" if target.is_dir() else None
    try:
        s = write_run_mcap(out, tlog, can_log=can_log, trajectory=trajectory, grid_map=grid_map,
                           robot_log=robot_log if robot_log is not None and robot_log.is_file() else None)
    except McapError as exc:
        raise CliError(str(exc)) from None
    except (OSError, ValueError) as exc:
        raise CliError(f"{out}: {exc}") from None
    print(f"{out}: {s.mavlink_messages} MAVLink messages, {s.can_frames} CAN frames, "
          f"{s.truth_samples} ground-truth samples, {len(s.messages)} topics"
          + ("" if grid_map is not None else " (no map)"))
    return 0
