"""`qnav sweep`: the learning-rate study (the paper's Fig. 5).

Trains every learning rate in --lrs with --seeds seeds each (and every
point of the --space search space), evaluates each greedy policy on the map,
and writes DIR/sweep.json, DIR/sweep.png (learning curves per eta; greedy
success and final average return against eta) and DIR/campaign.json (engine,
workers, nodes, wall time). For the cell encoding it also runs the same
learning rates and seeds with greedy checkpoints along training, with and
without the epsilon schedule (`ground_station.lab.study`), and writes
DIR/curves.png and DIR/curves.json: training steps to --threshold greedy
success against eta, and greedy success and the mean max-Q of the visited
states along training per eta (the paper's Fig. 5), each with bootstrapped
95 % CIs over the seeds (--no-curves skips this). Other training flags apply to every run; as in
`qnav train`, a flag left out takes the encoding's recipe
(its kind's `recipe`, ground_station/learn/kinds.py), else its default.

The runs go to all local cores by default (--engine local), or to Ray
(--engine ray: a private local instance, or a cluster with --ray-address;
--tune runs them as a resumable Ray Tune experiment). sweep.json depends only
on the seeded runs: the same command gives the same file on every engine.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.lab.campaign.engines import add_engine_arguments
    from ground_station.learn.config import add_config_arguments, recipe_defaults

    p = sub.add_parser("sweep", help="learning-rate study over several seeds (figure + JSON)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, metavar="DIR", help="folder for sweep.json and sweep.png")
    p.add_argument("--lrs", default="0.1:0.9:0.1", help="learning rates, start:stop:step or a,b,c (default: 0.1:0.9:0.1)")
    p.add_argument("--seeds", type=int, default=3, help="seeds per learning rate (default: 3)")
    p.add_argument("--space", action="append", default=[], metavar="FIELD=KIND:VALUES",
                   help="also vary any training field: FIELD=grid:a,b,c, or sampled --samples times with "
                        "uniform:LO,HI, loguniform:LO,HI, int:LO,HI, choice:a,b,c (repeatable)")
    p.add_argument("--samples", type=int, default=1, help="random draws of the sampled --space axes (default: 1)")
    p.add_argument("--tune", action="store_true",
                   help="with --engine ray: run the jobs as a Ray Tune experiment in DIR/tune/ "
                        "(re-run the same command to resume an interrupted sweep)")
    add_engine_arguments(p, "training runs")
    p.add_argument("--processes", type=int, default=None, dest="workers", help=argparse.SUPPRESS)
    add_config_arguments(p, skip=("lr",))
    recipe_defaults(p)  # as qnav train: a flag left out takes the encoding's recipe (its kind's recipe, learn/kinds.py)
    p.add_argument("--epsilon", type=float, default=None,
                   help="constant exploration rate: sets both --epsilon-start and --epsilon-end")
    p.add_argument("--curves", action=argparse.BooleanOptionalAction, default=True,
                   help="cell encoding: also the steps-to-threshold and Q-value figures (curves.png; default on)")
    p.add_argument("--threshold", type=float, default=0.95,
                   help="--curves: greedy success threshold (default: 0.95)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ground_station.errors import CliError
    from ground_station.lab.campaign.engines import engine_from_args
    from ground_station.lab.campaign.space import label, parse_axis
    from ground_station.lab.campaign.space import points as space_points
    from ground_station.lab.sweep import parse_lrs, sweep, with_values, write_sweep
    from ground_station.learn.cell.trainer import CellProblem
    from ground_station.learn.config import config_from_recipe_args, validate_config
    from ground_station.maps import MapError, load_map

    cfg = config_from_recipe_args(args)
    if args.epsilon is not None:
        cfg.epsilon_start = cfg.epsilon_end = args.epsilon
    if args.seeds < 1:
        raise CliError(f"--seeds must be >= 1, got {args.seeds}")
    if args.tune and args.engine != "ray":
        raise CliError("--tune needs --engine ray")
    try:
        lrs = parse_lrs(args.lrs)
        points = space_points([parse_axis(a) for a in args.space], args.samples, cfg.seed)
        for point in points:
            validate_config(with_values(cfg, **point))
        gridmap = load_map(cfg.map)
        if cfg.encoding == "cell":  # the goals resolve, every one reachable (else a worker's traceback)
            CellProblem.build(gridmap, cfg.options.targets or None)
    except (MapError, ValueError) as exc:
        raise CliError(str(exc)) from None
    t0 = time.perf_counter()
    with engine_from_args(args) as engine:
        data = sweep(cfg, lrs, args.seeds, engine, progress=True, points=points if args.space else None,
                     tune_dir=Path(args.out) / "tune" if args.tune else None)
    write_sweep(args.out, data)
    c = data["campaign"]
    print(f"sweep {cfg.encoding} on {cfg.map}: {len(points)} point(s) x {len(lrs)} learning rates x "
          f"{args.seeds} seeds = {c['jobs']} runs of {cfg.steps:,} steps in {time.perf_counter() - t0:.1f} s")
    print(f"campaign: engine {c['engine']}, {c['workers']} workers on {len(c['nodes'])} node(s), "
          f"{c['wall_s']:.1f} s wall, {c['job_s']:.1f} s of job time, "
          f"speedup over one core {c['speedup_over_one_core']:.2f}x")
    print(f"mean [bootstrapped 95 % CI] over {args.seeds} seeds")
    print(f"{'eta':>5}  {'greedy success':>22}  {'path ratio':>10}  {'final avg return':>26}  point")
    for s in data["summary"]:
        sc = s["success_ci95"] or [s["success_mean"]] * 2
        rc = s["final_avg_return_ci95"] or [s["final_avg_return_mean"]] * 2
        print(f"{s['lr']:>5g}  {s['success_mean']:.3f} [{sc[0]:.3f}, {sc[1]:.3f}]  {s['path_ratio_mean']:>10.3f}  "
              f"{s['final_avg_return_mean']:>8.3f} [{rc[0]:.3f}, {rc[1]:.3f}]  {label(s['point'])}")
    print(f"wrote {args.out}/sweep.json, {args.out}/campaign.json, {args.out}/sweep.png")
    if args.curves and cfg.encoding == "cell" and not args.space:
        _curves(args, cfg, lrs)
    return 0


def _curves(args: argparse.Namespace, cfg, lrs: list[float]) -> None:  # noqa: ANN001 - a TrainConfig
    """The study's Q-learning part on the sweep's rates and seeds: curves.json, curves.png."""
    import json

    from firmware_py.atomic import atomic_write
    from ground_station.lab.campaign.engines import engine_from_args
    from ground_station.lab.study import fmt_ci, plot_curves, study

    t0 = time.perf_counter()
    eval_every = max(100, cfg.steps // 100)
    with engine_from_args(args) as engine:
        data = study(cfg, lrs, args.seeds, learners=["q"], learner_lrs=[lrs[0]], eval_every=eval_every,
                     threshold=args.threshold, engine=engine, progress=True)
    out = Path(args.out)
    keep = {k: data[k] for k in ("map", "seeds", "lrs", "constant_epsilon", "eval_every", "threshold", "ci",
                                 "config", "lr_study")}
    atomic_write(out / "curves.json", json.dumps(keep, indent=1) + "\n")
    atomic_write(out / "curves.png", plot_curves(data))
    print(f"steps to {args.threshold:.0%} greedy success, mean [bootstrapped 95 % CI] over {args.seeds} seeds "
          f"(greedy checkpoint every {eval_every:,} steps; the budget {cfg.steps:,} where never reached):")
    print(f"{'eta':>5}  {'epsilon schedule':>30}  {'constant epsilon':>30}")
    rows = {(r["schedule"], r["lr"]): r["steps_to_threshold"] for r in data["lr_study"]}
    for lr in lrs:
        print(f"{lr:>5g}  {fmt_ci(rows[('decay', lr)], digits=0):>30}  {fmt_ci(rows[('constant', lr)], digits=0):>30}")
    print(f"curves in {time.perf_counter() - t0:.1f} s; wrote {args.out}/curves.json, {args.out}/curves.png")
