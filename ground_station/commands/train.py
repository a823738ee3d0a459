"""`qnav train`: train a Q table and write the run folder.

A flag left out takes the encoding's shipped recipe (its kind's `recipe` in
ground_station/learn/kinds.py; the cell recipe is the defaults shown below),
else the default shown below; so `qnav train --encoding sector-memory --map
M --seed N --out DIR` trains the shipped policy's recipe, and `qnav train
--recipe shipped-sector` (map paper10, seed 0 unless given) the shipped
policies/sector.qtab's table.

Writes DIR/q.npy (float64, n_states x n_actions), DIR/meta.json,
DIR/metrics.csv and DIR/learning_curve.png (see `ground_station.learn.train`).
Without --out the run folder is named for what it holds (CleanRL style):
runs/<map>-<encoding>-s<seed>-<YYYYmmdd-HHMMSS>. Integer options take 1e6.
"""

from __future__ import annotations

import argparse
import time


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.learn.config import add_config_arguments, recipe_defaults

    p = sub.add_parser("train", help="train a tabular Q policy (cell, sector or sector-memory encoding)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter, add_help=False)
    p.add_argument("-h", "--help", action=_HelpForEncoding, nargs=0,
                   help="show this help (after --encoding E: only the options training E reads)")
    from ground_station.learn.kinds import shipped_recipes

    p.add_argument("--recipe", choices=sorted(shipped_recipes()), default=None,
                   help="train a shipped policy's recipe (sets the encoding; other flags still win)")
    p.add_argument("--out", metavar="DIR", help="run folder to write (created if missing; default "
                   "runs/<map>-<encoding>-s<seed>-<time>)")
    add_config_arguments(p)
    recipe_defaults(p)  # a flag left out takes the encoding's recipe, else the default shown in its help
    p.add_argument("--epsilon", type=float, default=None,
                   help="constant exploration rate: sets both --epsilon-start and --epsilon-end")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    p.set_defaults(func=run)


class _HelpForEncoding(argparse.Action):
    """`qnav train --encoding E --help`: the options that training E reads, not every encoding's."""

    def __call__(self, parser, namespace, values, option_string=None):  # type: ignore[no-untyped-def]
        from ground_station.learn.config import applies_to, encodings

        encoding = getattr(namespace, "encoding", None)
        if encoding in encodings():
            for action in parser._actions:
                if action.dest != "encoding" and encoding not in applies_to(action.dest):
                    action.help = argparse.SUPPRESS
            parser.description = (f"`qnav train --encoding {encoding}`: train a Q table and write the run folder "
                                  "(the options below are those this encoding reads; `qnav train --help` lists "
                                  "every encoding's). A flag left out takes the encoding's shipped recipe "
                                  "(the kind's recipe, ground_station/learn/kinds.py).")
            parser.usage = f"qnav train --encoding {encoding} [--map MAP] [--steps N] [--seed N] [--out DIR] [options]"
            parser.formatter_class = lambda prog: argparse.HelpFormatter(prog, width=110, max_help_position=32)
            for action in parser._actions:
                if action.option_strings and action.nargs is None and action.metavar is None \
                        and action.choices is None and action.help != argparse.SUPPRESS:
                    action.metavar = "N" if action.type in (int, float) or action.dest == "steps" else "X"
            for group in parser._action_groups:
                if all(a.help == argparse.SUPPRESS for a in group._group_actions):
                    group.title = None
                    group._group_actions.clear()
        parser.print_help()
        parser.exit()


def default_run_dir(map_spec: str, encoding: str, seed: int) -> str:
    """runs/<map>-<encoding>-s<seed>-<time>; a map path contributes its file stem."""
    import re
    from pathlib import Path

    from ground_station.demo import default_run_dir as stamped_run_dir

    name = Path(map_spec).stem if map_spec.endswith(".map") else map_spec
    name = re.sub(r"[^A-Za-z0-9_.]+", "_", name).strip("_") or "map"
    return str(stamped_run_dir(f"{name}-{encoding}-s{seed}"))


def run(args: argparse.Namespace) -> int:
    from ground_station.errors import CliError
    from ground_station.learn import kinds
    from ground_station.learn.config import config_from_recipe_args
    from ground_station.learn.train import train, validate_config, write_run
    from ground_station.maps import MapError, load_map

    shipped = kinds.shipped_recipes()
    encoding = args.encoding or shipped.get(args.recipe or "", kinds.DEFAULT)
    if args.recipe and encoding != shipped[args.recipe]:
        raise CliError(f"--recipe {args.recipe} trains the {shipped[args.recipe]} encoding, "
                       f"not --encoding {encoding}")
    cfg = config_from_recipe_args(args, encoding)
    if args.epsilon is not None:
        cfg.epsilon_start = cfg.epsilon_end = args.epsilon
    try:
        validate_config(cfg)
        gridmap = load_map(cfg.map)
        t0 = time.perf_counter()
        res = train(cfg, gridmap, progress=not args.quiet)
    except (MapError, ValueError) as exc:
        raise CliError(str(exc)) from None
    out = args.out or default_run_dir(cfg.map, cfg.encoding, cfg.seed)
    meta = write_run(out, cfg, res)
    if not args.quiet:
        tail = res.successes[-max(1, len(res.successes) // 20):]
        learner = "" if cfg.learner == "q" else f" ({cfg.learner})"
        print(f"trained {cfg.encoding}{learner} on {gridmap.name}: {cfg.steps:,} steps, {len(res.returns):,} episodes "
              f"in {res.seconds:.2f} s ({meta['steps_per_s'] or 0:,.0f} steps/s; "
              f"{time.perf_counter() - t0:.2f} s with setup); "
              f"last 5% of episodes: success {tail.mean():.3f} (with exploration)")
        print(f"wrote {out}/q.npy {list(res.q.shape)}, meta.json, metrics.csv, learning_curve.png")
    return 0
