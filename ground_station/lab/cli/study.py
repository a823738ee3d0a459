"""`qnav study`: the learning-rate and learner study with statistics (cell encoding).

Trains --seeds seeds of Q-learning for every learning rate in --lrs, once
with the epsilon schedule (--epsilon-start -> --epsilon-end over
--epsilon-decay of the steps) and once with a constant --constant-epsilon;
then every learner in --learners at every rate in --learner-lrs. Every
--eval-every steps the greedy policy is rolled out from all (start, goal)
pairs. Reports, as means with bootstrapped 95 % confidence intervals over
the seeds: steps to --threshold greedy success against eta (both
schedules), greedy success and the mean max-Q of visited states (the
paper's Fig. 5) along training per eta, the learners' final success, steps
to threshold and kernel time, and one Q-learning run's greedy policy beside
BFS (optimal) with the time each takes.

With --sector-seeds N > 0, the same learners on the sector encoding (N
seeds each): the shipped sector recipe with --sector-steps steps (its epsilon and
learning-rate schedules scale with the steps), greedy checkpoints every
--sector-eval-every steps on --sector-sample fixed (start, goal, heading)
episodes of the twin; final success, steps to threshold, training time and
the path ratio against the octile grid path and against the any-angle
optimum of the disc robot (ground_station/lab/anyangle.py).

Writes DIR/study.json (depends only on the seeded runs: the same command
gives the same file on every engine), DIR/campaign.json (engine, wall and
job times, learner and BFS timings) and DIR/study.png; prints the tables
(markdown). Runs go to all local cores (--engine local) or Ray (--engine ray).
"""

from __future__ import annotations

import argparse
import time


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.lab.campaign.engines import add_engine_arguments
    from ground_station.lab.study_defaults import SECTOR_EVAL_EVERY, SECTOR_SAMPLE, SECTOR_STEPS
    from ground_station.learn.config import LEARNERS, add_config_arguments, int_arg

    p = sub.add_parser("study", help="learning-rate and learner study with bootstrapped 95%% CIs (cell encoding)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, metavar="DIR", help="folder for study.json, campaign.json, study.png")
    p.add_argument("--lrs", default="0.1:0.9:0.1", help="learning rates of the Q-learning study, start:stop:step "
                   "or a,b,c (default: 0.1:0.9:0.1)")
    p.add_argument("--seeds", type=int, default=20, help="seeds per point (default: 20)")
    p.add_argument("--constant-epsilon", type=float, default=0.1,
                   help="exploration rate of the runs without the schedule (default: 0.1)")
    p.add_argument("--learners", default=",".join(LEARNERS),
                   help=f"comma-separated learners to compare (default: {','.join(LEARNERS)})")
    p.add_argument("--learner-lrs", default="0.1,0.5", help="learning rates of the learner comparison (default: 0.1,0.5)")
    p.add_argument("--eval-every", type=int_arg, default=1000, help="greedy evaluation period in steps (default: 1000)")
    p.add_argument("--threshold", type=float, default=0.95, help="greedy success threshold (default: 0.95)")
    p.add_argument("--sector-learners", default=",".join(LEARNERS),
                   help=f"learners compared on the sector encoding (default: {','.join(LEARNERS)})")
    p.add_argument("--sector-seeds", type=int, default=0, help="seeds per sector learner, e.g. 20 (~2 min on two "
                   "cores); 0 = no sector part (default: 0)")
    p.add_argument("--sector-steps", type=int_arg, default=SECTOR_STEPS,
                   help=f"training steps of a sector run (default: {SECTOR_STEPS:,})")
    p.add_argument("--sector-eval-every", type=int_arg, default=SECTOR_EVAL_EVERY,
                   help=f"sector greedy checkpoint period in steps (default: {SECTOR_EVAL_EVERY:,})")
    p.add_argument("--sector-sample", type=int, default=SECTOR_SAMPLE,
                   help=f"episodes of every sector checkpoint (default: {SECTOR_SAMPLE})")
    add_engine_arguments(p, "training runs")
    add_config_arguments(p, skip=("lr", "learner", "encoding"))
    p.set_defaults(func=run, map="paper10", targets="A,B,C,D", steps=100_000)


def run(args: argparse.Namespace) -> int:
    from ground_station.errors import CliError
    from ground_station.lab.campaign.engines import engine_from_args
    from ground_station.lab.study import study, tables, write_study
    from ground_station.lab.sweep import parse_lrs
    from ground_station.learn.cell.trainer import CellProblem
    from ground_station.learn.config import LEARNERS, config_from_recipe_args, validate_config
    from ground_station.maps import MapError, load_map

    cfg = config_from_recipe_args(args, "cell")  # a cell study: the cell recipe (its defaults)
    learners = [v.strip() for v in args.learners.split(",") if v.strip()]
    sector_learners = [v.strip() for v in args.sector_learners.split(",") if v.strip()]
    for flag, names in (("--learners", learners), ("--sector-learners", sector_learners)):
        bad = [v for v in names if v not in LEARNERS]
        if bad or not names:
            raise CliError(f"{flag}: unknown learner(s) {', '.join(bad) or '(none)'}; choose from {', '.join(LEARNERS)}")
    if args.seeds < 1 or args.eval_every < 1 or not 0 < args.threshold <= 1 or not 0 <= args.constant_epsilon <= 1:
        raise CliError("--seeds and --eval-every must be >= 1, --threshold in (0, 1], --constant-epsilon in [0, 1]")
    if args.sector_seeds < 0 or args.sector_steps < 1 or args.sector_eval_every < 1 or args.sector_sample < 1:
        raise CliError("--sector-seeds must be >= 0, --sector-steps, --sector-eval-every and --sector-sample >= 1")
    try:
        lrs = parse_lrs(args.lrs)
        learner_lrs = parse_lrs(args.learner_lrs)
        validate_config(cfg)
        CellProblem.build(load_map(cfg.map), cfg.options.targets or None)  # the goals resolve, every one reachable
    except (MapError, ValueError) as exc:
        raise CliError(str(exc)) from None
    t0 = time.perf_counter()
    with engine_from_args(args) as engine:
        data = study(cfg, lrs, args.seeds, constant_epsilon=args.constant_epsilon, learners=learners,
                     learner_lrs=learner_lrs, eval_every=args.eval_every, threshold=args.threshold,
                     sector_learners=sector_learners, sector_seeds=args.sector_seeds,
                     sector_steps=args.sector_steps, sector_eval_every=args.sector_eval_every,
                     sector_sample=args.sector_sample, engine=engine, progress=True)
    write_study(args.out, data)
    c = data["campaign"]
    print(tables(data))
    print()
    runs = f"{c['jobs']} runs ({cfg.steps:,} steps per cell run"
    if "sector" in data:
        sec = data["sector"]
        runs += f"; {sec['seeds'] * len(sec['learners'])} of them sector runs of {sec['steps']:,} steps"
    print(f"study on {cfg.map}: {runs}) in {time.perf_counter() - t0:.1f} s "
          f"(engine {c['engine']}, {c['workers']} workers, {c['wall_s']:.1f} s wall, {c['job_s']:.1f} s of job time)")
    print(f"wrote {args.out}/study.json, {args.out}/campaign.json, {args.out}/study.png")
    return 0
