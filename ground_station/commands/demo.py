"""`qnav demo`: the whole system on one machine, with embedded defaults.

Starts a python-can-remote hub on 127.0.0.1, `qnav-sim` (lockstep: fast and
deterministic; --realtime: paced at real time, to watch) and `qnav-robot` as
separate processes; uploads the shipped paper10 policy (or, with --train,
one trained and exported first) over MAVLink FTP; sends the mission A -> B
-> C -> D (a sector policy gets the planner's waypoints through them,
`--plan`), arms, sets Auto; with --obstacles K / --movers M the sim adds
unmapped discs on the path and moving discs (scenario.json, drawn in
trajectory.png); shows the monitor until the mission completes (or a fault,
or the timeout); prints a summary: targets reached, time, collisions, and
where the trajectory PNG, the .tlog and the CAN log are. Every process it
started is stopped on exit, error or Ctrl-C.

Outputs go to runs/demo-<timestamp>/ (or --out DIR): demo.tlog (MAVLink,
both directions), can.blf (every CAN frame, sim-time stamps), can.log (the
same frames in candump -L format: `cantools decode firmware_py/qnav.dbc <
can.log`), trajectory.csv / trajectory.png (the sim's ground truth), robot/
(the robot's file store), robot_stats.json, sim.log, robot.log,
summary.json. `qnav report runs/demo-.../demo.tlog` plots the run from the
telemetry.

Exit status: 0 all targets reached without a collision, 1 not, 2 bad
arguments, 130 interrupted. --headless --json prints only the summary JSON
on stdout (targets_reached, targets_total, collisions, sim_seconds,
wall_seconds, ...); progress goes to stderr.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from firmware_py.shipped_policies import policy_file_arg


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="one-command demo: hub + sim + robot, upload, mission A-D, monitor, summary",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--realtime", action="store_true",
                   help="run the sim at real-time factor 1 (default: lockstep, as fast as the machine allows)")
    p.add_argument("--headless", action="store_true",
                   help="no dashboard: a status line per second on stderr (automatic without a terminal)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    p.add_argument("--train", action="store_true",
                   help="train and export a cell policy first (progress bar) instead of the shipped one")
    p.add_argument("--train-steps", type=int, default=3_000_000, metavar="N",
                   help="Q-learning steps with --train (default %(default)s)")
    p.add_argument("--policy", type=policy_file_arg, metavar="FILE.qtab",
                   help="policy to upload: a file or policies:NAME (default policies:paper10_cell, shipped)")
    p.add_argument("--targets", default="A,B,C,D", metavar="A,B,...",
                   help="mission: paper10 targets in visiting order (default %(default)s)")
    p.add_argument("--out", type=Path, metavar="DIR", help="run folder (default runs/demo-<timestamp>/)")
    p.add_argument("--timeout", type=float, metavar="S",
                   help="wall seconds to wait for the mission (default 120; 400 with --realtime)")
    p.add_argument("--seed", type=int, default=0, help="sim noise and obstacle placement seed (default %(default)s)")
    p.add_argument("--obstacles", type=int, default=0, metavar="K",
                   help="unmapped static discs on or beside the planned path (ground_station/nav/obstacles.py)")
    p.add_argument("--movers", type=int, default=0, metavar="M", help="moving discs (pedestrian pace)")
    p.add_argument("--profile", type=Path, metavar="FILE.toml",
                   help="robot profile (docs/robot-profile.md): the robot drives through its backends and the sim "
                        "plays the same boards, e.g. firmware_py/profiles/odrive.toml (default: qnav's own frames)")
    plan = p.add_mutually_exclusive_group()
    plan.add_argument("--plan", dest="plan", action="store_const", const=True, default=None,
                      help="send the planner's waypoints through the targets (default for sector policies)")
    plan.add_argument("--no-plan", dest="plan", action="store_const", const=False,
                      help="send the targets alone (default for cell policies)")
    p.set_defaults(func=run)


def _print_summary(s, out) -> None:
    verdict = "OK" if s.ok else "FAILED"
    sim = f"{s.sim_seconds:.1f} s sim" if s.sim_seconds is not None else "sim time -"
    mission_wall = f", {s.mission_wall_seconds:.1f} s wall" if s.mission_wall_seconds is not None else ""
    print(f"\nqnav demo {verdict}: {s.result}", file=out)
    print(f"  targets reached  {s.targets_reached} of {s.targets_total} ({' -> '.join(s.targets)})", file=out)
    print(f"  mission time     {sim}{mission_wall} ({s.mode}); whole demo {s.wall_seconds:.1f} s wall", file=out)
    if s.planned:
        print(f"  mission          {s.mission_items} planned waypoints", file=out)
    if s.scenario:
        print(f"  obstacles        {len(s.scenario['discs'])} unmapped discs, {len(s.scenario['movers'])} movers "
              f"(scenario.json)", file=out)
    print(f"  collisions       {s.collisions if s.collisions is not None else 'unknown (no trajectory)'}",
          file=out)
    print(f"  policy           {s.policy} (id {s.policy_id or '-'}), upload "
          f"{'-' if s.upload_seconds is None else f'{s.upload_seconds:.1f} s'}", file=out)
    for label, path in (("trajectory PNG", s.trajectory_png), ("tlog", s.tlog), ("CAN log", s.can_log),
                        ("trajectory CSV", s.trajectory_csv), ("run folder", s.run_dir)):
        print(f"  {label:<16} {path or '-'}", file=out)
    if s.tlog:
        print(f"  report: qnav report {s.tlog} --out {Path(s.run_dir) / 'report'}", file=out)


def run(args: argparse.Namespace) -> int:
    import signal

    from ground_station.demo import (
        EXIT_FAILED,
        EXIT_INTERRUPTED,
        EXIT_OK,
        DemoError,
        DemoOptions,
        run_demo,
    )
    from ground_station.errors import CliError

    targets = tuple(t.strip() for t in args.targets.split(",") if t.strip())
    if not targets:
        raise CliError("--targets is empty")
    if args.timeout is not None and not args.timeout > 0:
        raise CliError(f"--timeout must be positive, got {args.timeout:g}")
    if args.train and args.policy:
        raise CliError("--train and --policy exclude each other")
    if args.obstacles < 0 or args.movers < 0:
        raise CliError("--obstacles and --movers must be >= 0")
    if args.train_steps < 1:
        raise CliError(f"--train-steps must be >= 1, got {args.train_steps}")
    if args.profile is not None:  # checked here: a bad file is one line before any process starts
        from firmware_py.profile import ProfileError, load_profile

        try:
            load_profile(args.profile)
        except ProfileError as exc:
            raise CliError(f"--profile {exc}") from None
    headless = args.headless or not (sys.stdout.isatty() and sys.stdin.isatty())
    if headless and not args.headless:
        print("qnav demo: no terminal, running headless", file=sys.stderr)
    opts = DemoOptions(targets=targets, policy=args.policy, train=args.train, train_steps=args.train_steps,
                       realtime=args.realtime, headless=headless, out=args.out, timeout_s=args.timeout,
                       seed=args.seed, obstacles=args.obstacles, movers=args.movers, plan=args.plan,
                       profile=args.profile.resolve() if args.profile is not None else None)

    def say(line: str) -> None:
        print(f"qnav demo: {line}", file=sys.stderr, flush=True)

    def status(line: str) -> None:
        print(f"  {line}", file=sys.stderr, flush=True)

    def on_term(_sig, _frame):  # a plain `kill`: clean up like Ctrl-C
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        summary = run_demo(opts, say=say, status=status)
    except DemoError as exc:
        raise CliError(str(exc)) from None
    finally:
        signal.signal(signal.SIGTERM, previous)
    if args.json:
        print(summary.to_json())
    else:
        _print_summary(summary, sys.stdout)
    if summary.result == "interrupted":
        return EXIT_INTERRUPTED
    return EXIT_OK if summary.ok else EXIT_FAILED
