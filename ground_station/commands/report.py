"""`qnav report FILE.tlog`: summary JSON and PNG plots of a recorded run.

A `candump -L` log (can-utils) instead gives CAN-level facts: frames per
message and per sim tick, motor commands, controller states, e-stops
(ground_station/monitor/canlog.py); printed, or as JSON with --json.

Writes into --out (default `out/report-<tlog name>/`): summary.json,
trajectory.png, distance_to_goal.png, actions.png, timing.png (a plot whose
data is not in the recording is skipped and listed under plots_skipped).

Times are the robot's clock (its time_boot_ms: sim time in HIL) when the
recording carries it, else the tlog's receive stamps; the summary names the
clock. One vehicle per report: the first robot heard or --target-system;
frames of other systems, or of a second process with the same system id, are
ignored and counted (a warning line).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="plots + summary JSON from a .tlog; CAN facts from a candump -L log",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("tlog", metavar="FILE.tlog", help="telemetry recording (qnav monitor --tlog, qnav demo, MAVProxy) "
                   "or a candump -L log")
    p.add_argument("--out", metavar="DIR", help="output directory (default out/report-<tlog name>)")
    p.add_argument("--map", metavar="NAME|PATH", default=None,
                   help="map under the trajectory: built-in name, generator spec or .map path; 'none' for no "
                        "map (default: the map in summary.json beside the tlog - a qnav demo run - else none, "
                        "with a note; a warning names a map the run does not fit)")
    p.add_argument("--cell-size", type=float, default=0.5, metavar="M", help="map cell size in metres (default 0.5)")
    p.add_argument("--json", action="store_true", help="print the summary JSON instead of a short text summary")
    p.add_argument("--target-system", type=int, default=None, metavar="SYSID",
                   help="report on this system id (default: the first robot in the recording)")
    p.add_argument("--clock", choices=("auto", "robot", "wall"), default="auto",
                   help="time base: robot = its time_boot_ms (sim time in HIL), wall = tlog stamps "
                        "(default auto: robot when recorded)")
    p.set_defaults(func=run)


def _run_map(tlog: Path) -> str | None:
    """The map a `qnav demo` run folder names in its summary.json (None: none found)."""
    summary = tlog.parent / "summary.json"
    try:
        name = json.loads(summary.read_text()).get("map") if summary.is_file() else None
    except (OSError, ValueError, AttributeError):
        return None
    return name if isinstance(name, str) and name else None


def _misfit(poses, grid_map, share: float = 0.05) -> tuple[int, int] | None:
    """(bad, total) when more than `share` of the recorded positions are off the
    map or inside its occupied cells; None when the run fits (or there is no map)."""
    if grid_map is None or not poses:
        return None
    h, w = grid_map.occ.shape
    cs = grid_map.cell_size_m
    bad = 0
    for _t, x, y, *_ in poses:
        col, row = int(x // cs), h - 1 - int(y // cs)
        if not (0 <= col < w and 0 <= row < h) or grid_map.occ[row, col]:
            bad += 1
    return (bad, len(poses)) if bad > share * len(poses) else None


def run(args: argparse.Namespace) -> int:
    from ground_station.commands.monitor import _load_map
    from ground_station.errors import CliError
    from ground_station.monitor.report import analyse, write_report

    if not os.path.isfile(args.tlog):
        raise CliError(f"no such tlog: {args.tlog}")
    from ground_station.monitor.canlog import analyse_candump, is_candump_log, text_summary

    if is_candump_log(args.tlog):
        summary = analyse_candump(args.tlog)
        print(json.dumps(summary, indent=2) if args.json else "\n".join(text_summary(summary)))
        return 0
    if args.cell_size <= 0:
        raise CliError(f"--cell-size must be > 0, got {args.cell_size}")
    map_spec = args.map or _run_map(Path(args.tlog))
    grid_map = _load_map(map_spec or "none", args.cell_size)  # a bad --map is refused before the long read
    rec = analyse(args.tlog, progress=True, sysid=args.target_system, clock=args.clock)
    if rec.messages == 0:  # the real error first, and alone: no note about a map for a file that is no tlog
        raise CliError(f"{args.tlog}: no MAVLink messages from a vehicle (is it a .tlog?)")
    if map_spec is None:  # a tlog alone does not say its map: a blank field, not a guess drawn through walls
        print("qnav report: no map given (and no qnav demo summary.json beside the tlog): the trajectory is "
              "drawn on a blank field; give --map NAME|PATH", file=sys.stderr)
    misfit = _misfit(rec.pose, grid_map)
    if misfit:
        print(f"qnav report: warning: {misfit[0]} of {misfit[1]} positions lie outside map {grid_map.name} or in "
              f"its walls: was the run on another map? (give --map)", file=sys.stderr)
    out = Path(args.out) if args.out else Path("out") / f"report-{Path(args.tlog).stem}"
    try:
        summary = write_report(rec, out, grid_map)
    except OSError as exc:
        raise CliError(f"cannot write report to {out}: {exc}") from exc
    ignored = summary["ignored"]
    if ignored["other_systems"] or ignored["clock_behind_frames"]:
        others = ", ".join(f"system {k}: {v}" for k, v in ignored["other_systems"].items())
        behind = ignored["clock_behind_frames"]
        print(f"qnav report: warning: reporting system {summary['vehicle_sysid']} only; ignored "
              + "; ".join(x for x in (f"frames of other systems ({others})" if others else "",
                                      f"{behind} frames whose clock ran behind (a second process with the "
                                      f"same system id?)" if behind else "") if x), file=sys.stderr)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    ttg = summary["time_to_last_goal_s"]
    print(f"{args.tlog}: system {summary['vehicle_sysid']}, {summary['duration_s']:.1f} s ({summary['clock']}"
          f"; {summary['wall_duration_s']:.1f} s wall), "
          f"last goal at {'-' if ttg is None else f'{ttg:.1f} s'} after the first move")
    print(f"  goals reached {summary['goals_reached']}, "
          f"path {summary['path_length_m']:.2f} m, stops {summary['stops']}, faults {summary['faults']}, "
          f"link loss {summary['link']['loss_pct']:.1f}%")
    for name, path in summary["plots"].items():
        print(f"  {name:<17} {path}")
    for name, why in summary["plots_skipped"].items():
        print(f"  {name:<17} skipped: {why}")
    print(f"  {'summary':<17} {summary['summary_json']}")
    return 0
