"""`qnav eval`: greedy rollouts of a trained run against shortest paths.

Every (start, goal) pair of the map (a seeded sample of --sample pairs on
large maps): success rate, path length / shortest (mean, max), timeouts,
collisions, loops, beside the greedy nearest-free-neighbour baseline. Sector
runs: the main figures follow the ground station's planned waypoints
(`ground_station.maps.planner`, what the robot gets as a mission); the same
policy steering on the goal bearing alone is reported beside them
(`direct_*` keys), and the baseline is a hand-written seek table on the same
waypoints. Sector-memory runs are judged in the direct setting only (goal
bearing and distance, no waypoints: `success_rate` is the direct figure) and
add `wall_share`, the share of periods spent following a wall
(docs/training.md, sector-memory; figures in docs/results.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ground_station.errors import CliError


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="evaluate a trained run (greedy rollouts vs shortest paths)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir", metavar="DIR", help="run folder written by qnav train")
    p.add_argument("--map", metavar="NAME|PATH",
                   help="map to evaluate on (default: the training map recorded in DIR/meta.json)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--sample", type=int, default=None, metavar="N",
                   help="evaluate a seeded sample of N (start, goal) pairs instead of all")
    p.add_argument("--seed", type=int, default=0, help="seed of the sample (default: 0)")
    p.add_argument("--profile", metavar="FILE.toml", default=None,
                   help="robot profile the twin plays (docs/robot-profile.md; default: the robot the run was "
                        "trained for, meta.json `robot`, the built-in robot for runs without one)")
    p.add_argument("--plot", metavar="FILE", default=None,
                   help="cell runs: write a PNG of the greedy policy (an arrow per cell, one panel per goal)")
    p.set_defaults(func=run)


def _fmt(v) -> str:
    if v is None:
        return "-"
    return f"{v:.3f}" if isinstance(v, float) else str(v)


def run(args: argparse.Namespace) -> int:
    from ground_station.learn.evaluate import evaluate_run
    from ground_station.maps import MapError, load_map

    if args.sample is not None and args.sample < 1:
        raise CliError(f"--sample must be >= 1, got {args.sample}")
    _check_run_dir(args.run_dir)
    if args.map is None:
        args.map = _run_map(args.run_dir)
    try:
        gridmap = load_map(args.map)
        profile = None
        if args.profile is not None:
            from firmware_py.profile import load_profile

            profile = load_profile(args.profile)
        rep = evaluate_run(args.run_dir, gridmap, sample=args.sample, seed=args.seed, profile=profile)
    except (MapError, ValueError) as exc:
        raise CliError(str(exc)) from None
    if args.plot:
        _plot(args, gridmap)
    if args.json:
        print(json.dumps(rep, indent=1))
        return 0
    base = rep.get("baseline", {})
    direct = rep.get("direct")  # sector: the same policy without waypoint guidance
    keys = ["success_rate", "path_ratio_mean", "path_ratio_max", "timeouts", "collisions", "loops", "episodes"]
    if "wall_share" in rep:
        keys.append("wall_share")
    print(f"== qnav eval {args.run_dir} on {gridmap.name} ({rep.get('encoding')}) ==")
    if direct is not None:
        print("policy and baseline (hand-written seek) follow the planned waypoints; direct = policy on the goal bearing")
    print(f"{'':<16}{'policy':>10}{'baseline':>10}" + (f"{'direct':>10}" if direct is not None else ""))
    for k in keys:
        print(f"{k:<16}{_fmt(rep.get(k)):>10}{_fmt(base.get(k)):>10}"
              + (f"{_fmt(direct.get(k)):>10}" if direct is not None else ""))
    if rep.get("per_target"):
        print("per target success: " + ", ".join(f"{k} {_fmt(v)}" for k, v in rep["per_target"].items()))
    if rep.get("failures"):
        print("failures: " + ", ".join(f"{k} {v}" for k, v in rep["failures"].items()))
    if args.plot:
        print(f"wrote {args.plot}")
    return 0


def _check_run_dir(run_dir: str) -> None:
    """A one-line error unless `run_dir` is a folder (a policy file or a map is named as such)."""
    path = Path(run_dir)
    if path.is_dir() or not path.exists():
        return  # a missing folder: _run_map / evaluate_run name what is missing
    what = {".qtab": "a policy file", ".map": "a map", ".tlog": "a telemetry log"}.get(path.suffix.lower(), "a file")
    hint = (f"; `qnav policy inspect {run_dir}` checks a policy, `qnav export DIR` makes one from a run"
            if path.suffix.lower() == ".qtab" else "")
    raise CliError(f"{run_dir} is {what}: qnav eval takes a training run folder (qnav train --out DIR){hint}")


def _run_map(run_dir: str) -> str:
    """The map a run was trained on (meta.json `map`), or a one-line error."""
    meta_path = Path(run_dir) / "meta.json"
    try:
        meta = json.loads(meta_path.read_text())
    except FileNotFoundError:
        raise CliError(f"{meta_path}: no such file (is {run_dir} a qnav train run folder?)") from None
    except (OSError, ValueError) as exc:
        raise CliError(f"{meta_path}: cannot read: {exc}") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("map"), str):
        raise CliError(f"{meta_path} names no training map; pass --map")
    return meta["map"]


def _plot(args: argparse.Namespace, gridmap) -> None:
    from firmware_py.atomic import atomic_write
    from ground_station.learn.evaluate import plot_run

    try:
        png = plot_run(args.run_dir, gridmap)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    atomic_write(Path(args.plot), png, make_parents=True)
