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

Writes DIR/study.json (depends only on the seeded runs: the same command
gives the same file on every engine), DIR/campaign.json (engine, wall and
job times, learner and BFS timings) and DIR/study.png; prints the tables
(markdown). Runs go to all local cores (--engine local) or Ray (--engine ray).
"""

from __future__ import annotations

import argparse
import time


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.campaign.engines import add_engine_arguments
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
    add_engine_arguments(p, "training runs")
    add_config_arguments(p, skip=("lr", "learner", "encoding"))
    p.set_defaults(func=run, map="paper10", targets="A,B,C,D", steps=100_000)


def run(args: argparse.Namespace) -> int:
    from ground_station.campaign.engines import engine_from_args
    from ground_station.errors import CliError
    from ground_station.learn.config import LEARNERS, config_from_recipe_args, validate_config
    from ground_station.learn.study import study, tables, write_study
    from ground_station.learn.sweep import parse_lrs
    from ground_station.learn.train import CellProblem
    from ground_station.maps import MapError, load_map

    cfg = config_from_recipe_args(args, "cell")  # a cell study: the cell recipe (its defaults)
    learners = [v.strip() for v in args.learners.split(",") if v.strip()]
    bad = [v for v in learners if v not in LEARNERS]
    if bad or not learners:
        raise CliError(f"--learners: unknown learner(s) {', '.join(bad) or '(none)'}; choose from {', '.join(LEARNERS)}")
    if args.seeds < 1 or args.eval_every < 1 or not 0 < args.threshold <= 1 or not 0 <= args.constant_epsilon <= 1:
        raise CliError("--seeds and --eval-every must be >= 1, --threshold in (0, 1], --constant-epsilon in [0, 1]")
    try:
        lrs = parse_lrs(args.lrs)
        learner_lrs = parse_lrs(args.learner_lrs)
        validate_config(cfg)
        CellProblem.build(load_map(cfg.map), cfg.targets or None)  # the goals resolve, every one reachable
    except (MapError, ValueError) as exc:
        raise CliError(str(exc)) from None
    t0 = time.perf_counter()
    with engine_from_args(args) as engine:
        data = study(cfg, lrs, args.seeds, constant_epsilon=args.constant_epsilon, learners=learners,
                     learner_lrs=learner_lrs, eval_every=args.eval_every, threshold=args.threshold,
                     engine=engine, progress=True)
    write_study(args.out, data)
    c = data["campaign"]
    print(tables(data))
    print()
    print(f"study on {cfg.map}: {c['jobs']} runs of {cfg.steps:,} steps in {time.perf_counter() - t0:.1f} s "
          f"(engine {c['engine']}, {c['workers']} workers, {c['wall_s']:.1f} s wall, {c['job_s']:.1f} s of job time)")
    print(f"wrote {args.out}/study.json, {args.out}/campaign.json, {args.out}/study.png")
    return 0
