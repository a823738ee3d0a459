"""`qnav export DIR --dtype int8|int16 --out FILE.qtab`: quantise a trained float Q-table into the
robot's int policy file and judge what it cost.

Reads DIR/q.npy and DIR/meta.json (written by `qnav train`), quantises symmetrically (one scale per
table, or per state with --per-state-scale), keeps the float table's greedy choice where rounding tied
a unique maximum (--no-preserve-argmax: plain rounding), validates the bytes with the robot's own
loader, writes FILE atomically and prints one JSON object: `bytes`, `dtype`, `argmax_agreement`,
`tie_rate` (beside `float_tie_rate`, `rounding_ties`, `argmax_fixes`), and greedy-rollout
`success_rate` / `path_ratio_mean` for the float and the int table side by side (`{"float": ...,
"int": ...}`), on the training map unless --map says otherwise. The int rollouts use the table
exactly as the robot loaded it (argmax, ties to the lowest index).
"""

from __future__ import annotations

import argparse
import json
import math


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="quantise a trained table into a .qtab policy file",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dir", metavar="DIR", help="training run folder (q.npy + meta.json)")
    p.add_argument("--dtype", choices=("int8", "int16"), default="int8", help="int type (default %(default)s)")
    p.add_argument("--out", required=True, metavar="FILE.qtab", help="policy file to write (atomically)")
    p.add_argument("--per-state-scale", action="store_true",
                   help="one scale per state instead of one per table")
    p.add_argument("--preserve-argmax", action=argparse.BooleanOptionalAction, default=True,
                   help="where rounding ties a row's unique float argmax, put the tied competitors 1 LSB below it, "
                        "so the robot's greedy choice is the float table's (default on; off: plain rounding)")
    p.add_argument("--policy-id", type=lambda s: int(s, 0), default=None,
                   help="policy id (u32, e.g. 0x1234); default: CRC32 of encoder + table")
    p.add_argument("--map", default=None, metavar="NAME|PATH",
                   help="map for the rollout comparison (default: the training map)")
    p.add_argument("--sample", type=int, default=None,
                   help="evaluate a seeded sample of N episodes instead of all")
    p.add_argument("--seed", type=int, default=0, help="seed for --sample (default %(default)s)")
    p.add_argument("--no-rollouts", action="store_true", help="skip the rollout comparison")
    p.add_argument("--profile", metavar="FILE.toml", default=None,
                   help="the robot the file is for (docs/robot-profile.md): refused, naming both values, if it "
                        "cannot run the policy (firmware_py.needs); the rollouts play it")
    p.add_argument("--local-planner", nargs="?", const="{}", default=None, metavar="JSON",
                   help="sector policies: the robot re-plans round obstacles its map does not show "
                        "(firmware_py.kinds.sector); optional JSON object of planner parameters, default the defaults")
    p.set_defaults(func=run)


def _clean(x):
    """JSON has no NaN: report an undefined figure as null."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_clean(v) for v in x]
    return x


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from firmware_py.atomic import atomic_write
    from firmware_py.policy import PolicyError, load_policy
    from ground_station.errors import CliError
    from ground_station.learn import export

    try:
        run_ = export.load_run(args.run_dir)
        trained = export.trained_for(run_)
        qt = export.quantise(run_.q, args.dtype, per_state=args.per_state_scale,
                             preserve_argmax=args.preserve_argmax)
        meta = export.file_metadata(run_, qt)
        if args.local_planner is not None:
            meta[export.META_PLANNER] = export.planner_metadata(args.local_planner, run_.encoder.kind, meta)
        data = export.policy_bytes(qt, run_.encoder, goals=run_.goals, cell_mm=run_.cell_mm,
                                   metadata=meta, policy_id=args.policy_id,
                                   created=export.created_time(run_.meta),
                                   control_period_us=export.control_period_us(run_),
                                   map_geometry=export.map_geometry(run_), trained=trained)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    try:
        pol = load_policy(data)  # the robot's loader is the judge of what we ship
    except PolicyError as exc:
        raise CliError(f"exported file fails the robot's loader: {exc}") from None
    if args.profile is not None:  # the robot's own check, before anything is written
        from firmware_py.needs import needs_mismatch, needs_of
        from firmware_py.profile import load_profile
        from ground_station.learn.evaluate import on_robot

        try:
            profile = load_profile(args.profile)
        except ValueError as exc:
            raise CliError(str(exc)) from None
        why = needs_mismatch(needs_of(pol), profile)
        if why:
            raise CliError(f"--profile {args.profile}: {why}")
        run_ = on_robot(run_, profile)
    try:
        atomic_write(args.out, data)
    except OSError as exc:
        raise CliError(f"cannot write {args.out}: {exc.strerror or exc}") from None

    report = {"out": args.out, "bytes": len(data), "dtype": qt.dtype, "n_states": pol.n_states,
              "n_actions": pol.n_actions, "encoding": pol.kind, "per_state_scales": qt.state_scales is not None,
              "scale": qt.scale, "policy_id": f"0x{pol.policy_id:08x}", "crc32": f"0x{pol.crc:08x}",
              **export.compare(run_.q, qt)}
    if not args.no_rollouts:
        from ground_station.learn.evaluate import evaluate_table
        from ground_station.maps import MapError, load_map

        int_q = np.frombuffer(pol.table, dtype=np.dtype(qt.dtype).newbyteorder("=")).reshape(
            pol.n_states, pol.n_actions).astype(np.float64)
        map_name = args.map or run_.meta.get("map")
        if not map_name:
            raise CliError(f"{args.run_dir}/meta.json names no map; pass --map")
        try:
            gridmap = load_map(map_name)
            r_float = evaluate_table(run_.q, run_, gridmap, sample=args.sample, seed=args.seed)
            r_int = evaluate_table(int_q, run_, gridmap, sample=args.sample, seed=args.seed)
        except (MapError, ValueError) as exc:
            raise CliError(f"rollouts: {exc}") from None
        report["map"] = gridmap.name
        for key in ("success_rate", "path_ratio_mean", "path_ratio_max", "collisions", "loops", "timeouts"):
            report[key] = {"float": r_float.get(key), "int": r_int.get(key)}
        report["episodes"] = r_float.get("episodes")
    print(json.dumps(_clean(report), indent=1))
    return 0
