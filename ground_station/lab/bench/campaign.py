"""`qnav bench campaign`: what parallel workers buy on a campaign of twin runs.

The campaign is `--runs` seeded twin runs: each evaluates a sector policy
greedily on `--episodes` seeded (start, goal, heading) episodes of the
kinematic twin (the job a navigation benchmark farms out). It runs once with
one worker (the baseline) and once with `--workers` workers on the same
engine, and reports the wall times, the speedup and whether both runs gave
the same result (they must: every job is seeded, results come back in job
order).
"""

from __future__ import annotations

import argparse
import json
import time
from typing import TYPE_CHECKING, cast

from firmware_py.kinds.sector.encoder import SectorEncoder

if TYPE_CHECKING:
    import numpy as np

    from firmware_py.policy import Policy


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.lab.campaign.engines import add_engine_arguments

    p = sub.add_parser("campaign", help="speedup of N workers over one on a campaign of twin runs",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=200, help="twin runs in the campaign (default: 200)")
    p.add_argument("--episodes", type=int, default=2000, help="greedy twin episodes per run (default: 2000)")
    p.add_argument("--map", default="paper10", help="map (default: paper10)")
    p.add_argument("--policy", default="policies:sector", metavar="FILE",
                   help="sector policy, a .qtab file or policies:NAME (default: %(default)s)")
    add_engine_arguments(p, "twin runs", workers=2, workers_help="workers of the parallel run (the baseline has 1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", metavar="FILE", help="write the result as JSON")
    p.set_defaults(func=run)


def campaign_jobs(runs: int, episodes: int, map_name: str, policy: str, seed: int) -> list[dict]:
    """`runs` twin runs, run k seeded with seed + k."""
    return [{"map": map_name, "policy": policy, "episodes": episodes, "seed": seed + k} for k in range(runs)]


def float_table(pol: Policy) -> np.ndarray:
    """A loaded policy's Q-table as the floats its ints stand for (each row times its scale); the
    robot never needs it, it only compares ints."""
    import numpy as np

    ints = np.array([pol.row(s) for s in range(pol.n_states)], dtype=np.float64)
    scales = np.full(pol.n_states, pol.scale) if pol.state_scales is None else np.asarray(pol.state_scales, np.float64)
    return ints * scales[:, None]


def twin_run(job: dict) -> dict:
    """One campaign job: greedy twin rollouts of the policy on a seeded sample."""
    from firmware_py.policy import load_policy
    from ground_station.learn.sector.evaluate import evaluate_sector
    from ground_station.maps import load_map

    pol = load_policy(job["policy"])
    if pol.kind != "sector":
        raise ValueError(f"{job['policy']} is not a sector policy")
    q = float_table(pol)
    ev = evaluate_sector(q, load_map(job["map"]), cast(SectorEncoder, pol.encoder), seed=job["seed"],
                         sample=job["episodes"])
    return {"seed": job["seed"], "episodes": ev["episodes"], "success_rate": ev["success_rate"],
            "collisions": ev["collisions"]}


def run(args: argparse.Namespace) -> int:
    from firmware_py.shipped_policies import resolve_policy_spec
    from ground_station.errors import CliError
    from ground_station.lab.bench.common import report
    from ground_station.lab.campaign.engines import make_engine

    if args.runs < 1 or args.episodes < 1:
        raise CliError("--runs and --episodes must be >= 1")
    if args.workers < 2:
        raise CliError(f"--workers must be >= 2 (the baseline is 1 worker), got {args.workers}")
    try:
        jobs = campaign_jobs(args.runs, args.episodes, args.map, str(resolve_policy_spec(args.policy)), args.seed)
        twin_run(jobs[0])  # compile the kernels once, outside both timings (numba caches them on disk)
    except (OSError, ValueError) as exc:
        raise CliError(f"campaign job: {exc}") from None
    outcomes: dict[int, dict] = {}
    for workers in (1, args.workers):
        t0 = time.perf_counter()
        with make_engine(args.engine, workers, args.ray_address) as engine:
            results, stats = engine.map(twin_run, jobs, desc=f"{workers} worker(s)", unit="run")
        outcomes[workers] = {"wall_s": time.perf_counter() - t0, "stats": stats.as_dict(),
                             "digest": json.dumps(results, sort_keys=True)}
    base, par = outcomes[1], outcomes[args.workers]
    speedup = base["wall_s"] / par["wall_s"]
    same = base["digest"] == par["digest"]
    result = {"engine": args.engine, "runs": args.runs, "episodes_per_run": args.episodes,
              "policy": args.policy, "success_rate_mean": sum(r["success_rate"] for r in results) / len(results), "map": args.map, "seed": args.seed,
              "baseline_workers": 1, "workers": args.workers,
              "baseline_wall_s": base["wall_s"], "wall_s": par["wall_s"], "speedup": speedup,
              "identical_results": same, "nodes": par["stats"]["nodes"]}
    report("campaign", [
        ("campaign", f"{args.runs} twin runs x {args.episodes:,} episodes on {args.map}, seed {args.seed}"),
        ("engine", args.engine),
        ("wall s, 1 worker (baseline)", base["wall_s"]),
        (f"wall s, {args.workers} workers", par["wall_s"]),
        ("speedup", speedup),
        ("identical results", "yes" if same else "NO"),
    ], result, args.json)
    return 0 if same else 1
