"""`qnav sweep`: the learning-rate study (the paper's Fig. 5).

Trains every learning rate in --lrs with --seeds seeds each, on all CPU
cores, evaluates each greedy policy on the map, and writes DIR/sweep.json
and DIR/sweep.png (learning curves per eta; greedy success and final
average return against eta). Other training flags apply to every run.
"""

from __future__ import annotations

import argparse
import time


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.learn.config import add_config_arguments

    p = sub.add_parser("sweep", help="learning-rate study over several seeds (figure + JSON)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, metavar="DIR", help="folder for sweep.json and sweep.png")
    p.add_argument("--lrs", default="0.1:0.9:0.1", help="learning rates, start:stop:step or a,b,c (default: 0.1:0.9:0.1)")
    p.add_argument("--seeds", type=int, default=3, help="seeds per learning rate (default: 3)")
    p.add_argument("--processes", type=int, default=None, help="worker processes (default: all cores)")
    add_config_arguments(p, skip=("lr",))
    p.add_argument("--epsilon", type=float, default=None,
                   help="constant exploration rate: sets both --epsilon-start and --epsilon-end")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ground_station.errors import CliError
    from ground_station.learn.config import config_from_args, validate_config
    from ground_station.learn.sweep import parse_lrs, sweep, write_sweep
    from ground_station.maps import MapError, load_map

    cfg = config_from_args(args)
    if args.epsilon is not None:
        cfg.epsilon_start = cfg.epsilon_end = args.epsilon
    if args.seeds < 1:
        raise CliError(f"--seeds must be >= 1, got {args.seeds}")
    if args.processes is not None and args.processes < 1:
        raise CliError(f"--processes must be >= 1, got {args.processes}")
    try:
        lrs = parse_lrs(args.lrs)
        validate_config(cfg)
        load_map(cfg.map)
    except (MapError, ValueError) as exc:
        raise CliError(str(exc)) from None
    t0 = time.perf_counter()
    data = sweep(cfg, lrs, args.seeds, args.processes, progress=True)
    write_sweep(args.out, data)
    print(f"sweep {cfg.encoding} on {cfg.map}: {len(lrs)} learning rates x {args.seeds} seeds, "
          f"{cfg.steps:,} steps each, {data['processes']} processes, {time.perf_counter() - t0:.1f} s")
    print(f"{'eta':>5}  {'greedy success':>16}  {'path ratio':>10}  {'final avg return':>18}")
    for s in data["summary"]:
        print(f"{s['lr']:>5g}  {s['success_mean']:>8.3f} ± {s['success_std']:<5.3f}  {s['path_ratio_mean']:>10.3f}  "
              f"{s['final_avg_return_mean']:>9.3f} ± {s['final_avg_return_std']:<6.3f}")
    print(f"wrote {args.out}/sweep.json, {args.out}/sweep.png")
    return 0
