"""`qnav bench ceiling`: how many of a scenario's episodes could be finished at all,
beside the controllers on the same episodes (issue 47).

The episodes are `qnav bench nav`'s for the same options (seeded: the same
starts, goals, discs and movers). A privileged planner
(`ground_station.lab.nav.oracle`: it knows the discs and every mover's walk in
advance, turns on the spot in no time and keeps clear of the movers) searches
each for a way through the waypoints to the goal within the episode's budget;
the controllers (default learnt, seek_local, vfh_local) drive them on the
twin as in `qnav bench nav`. What the oracle solves is a lower bound on what
the scenario allows (it may miss a way: its docstring says where), so a
controller's success is measured against it: its failures the oracle
solved (the controller's to win) and those it did not (maybe none can).

Prints a table and writes JSON (`--json`): `scenario`, `oracle` and each
controller's summary (as `qnav bench nav`'s), `per_map` (episodes, oracle
solved, each controller's successes), and `episodes`: one row per episode
(map, index on it, the oracle's period or null, each controller's outcome).
"""

from __future__ import annotations

import argparse
from typing import Any

DEFAULT_CONTROLLERS = "learnt,seek_local,vfh_local"


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.lab.campaign.engines import add_engine_arguments

    p = sub.add_parser("ceiling", help="which scenario episodes a privileged planner finishes, beside the "
                                       "controllers", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--map", action="append", metavar="NAME|PATH", required=True, help="map (repeatable)")
    p.add_argument("--obstacles", type=int, default=3, metavar="K", help="static discs (default %(default)s)")
    p.add_argument("--movers", type=int, default=2, metavar="M", help="movers (default %(default)s)")
    p.add_argument("--no-yield", action="store_true", help="movers do not give way (as bench nav)")
    p.add_argument("--episodes", type=int, default=40, help="episodes per map (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="scenario seed (default %(default)s)")
    p.add_argument("--policy", default="policies:sector", metavar="FILE",
                   help="the learnt sector policy (default %(default)s)")
    p.add_argument("--controllers", default=DEFAULT_CONTROLLERS,
                   help="comma-separated, as bench nav's; '' for the oracle alone (default %(default)s)")
    p.add_argument("--batch", type=int, default=20, metavar="N", help="episodes per job (default %(default)s)")
    p.add_argument("--json", metavar="FILE", help="write the result (with per-episode rows) as JSON")
    add_engine_arguments(p, "episode batches")
    p.set_defaults(func=run)


def ceiling_job(job: dict) -> list[Any]:
    """One job: the oracle's periods (-1: no way found) or a controller's rows (`episodes.run_job`)."""
    from ground_station.lab.nav.episodes import run_job

    if job["kind"] != "oracle":
        return run_job(job)
    from firmware_py import robot_spec
    from ground_station.lab.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, PERIOD_S
    from ground_station.lab.nav.oracle import solve
    from ground_station.maps import load_map

    maps = {name: load_map(spec) for name, spec in job["maps"].items()}
    return [solve(ep, maps[ep.map], robot_spec.ROBOT_RADIUS_MM, BUDGET_BASE, BUDGET_FACTOR, PERIOD_S)
            for ep in job["episodes"]]


def run(args: argparse.Namespace) -> int:
    from firmware_py.policy import PolicyError, load_policy
    from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec
    from ground_station.errors import CliError
    from ground_station.lab.bench.common import report
    from ground_station.lab.campaign.engines import engine_from_args, write_campaign
    from ground_station.lab.nav.controllers import standard_controllers
    from ground_station.lab.nav.episodes import PERIOD_S, summarise, wilson95
    from ground_station.lab.nav.scenario import MOVER_SPEED_MM_S, MoverStyle, episodes
    from ground_station.maps import MapError, load_map

    if args.obstacles < 0 or args.movers < 0 or args.episodes < 1 or args.batch < 1:
        raise CliError("--obstacles/--movers must be >= 0, --episodes/--batch >= 1")
    names = tuple(c.strip() for c in args.controllers.split(",") if c.strip())
    try:
        path = resolve_policy_spec(args.policy)
        pol = load_policy(str(path))
        ctrls = standard_controllers(pol, names)
    except (PolicyError, ShippedPolicyError, OSError) as exc:
        raise CliError(f"policy {args.policy}: {exc}") from None
    except ValueError as exc:
        raise CliError(f"--controllers: {exc}") from None
    style = MoverStyle(speed=MOVER_SPEED_MM_S, yields=not args.no_yield)
    specs: dict[str, str] = {}
    eps = []
    try:
        for spec in args.map:
            gm = load_map(spec)
            specs[gm.name] = spec
            eps += episodes(gm, args.episodes, args.seed, args.obstacles, args.movers, movers=style)
    except (MapError, OSError) as exc:
        raise CliError(str(exc)) from None
    base = {"policy": str(path), "maps": specs}
    chunks = [eps[i:i + args.batch] for i in range(0, len(eps), args.batch)]
    jobs: list[dict[str, Any]] = [{**base, "kind": "oracle", "controller": "oracle", "episodes": c} for c in chunks]
    jobs += [{**base, "kind": "twin", "controller": c.name, "episodes": ch} for c in ctrls for ch in chunks]
    with engine_from_args(args) as engine:
        out, stats = engine.map(ceiling_job, jobs, desc="episodes", unit="batch")
    by: dict[str, list] = {}
    for job, res in zip(jobs, out, strict=True):
        by.setdefault(job["controller"], []).extend(res)
    periods = by["oracle"]
    solved = [p >= 0 for p in periods]
    index: dict[str, int] = {}
    rows: list[dict[str, Any]] = []
    for ep, p in zip(eps, periods, strict=True):
        i = index[ep.map] = index.get(ep.map, -1) + 1
        rows.append({"map": ep.map, "index": i, "oracle_s": round(p * PERIOD_S, 2) if p >= 0 else None,
                     **{c.name: by[c.name][len(rows)]["outcome"] for c in ctrls}})
    n = len(eps)
    k = sum(solved)
    result: dict = {
        "scenario": {"maps": list(specs), "obstacles": args.obstacles, "movers": args.movers,
                     "movers_yield": style.yields, "seed": args.seed, "episodes_per_map": args.episodes,
                     "definition": "ground_station/lab/nav/scenario.py; oracle: ground_station/lab/nav/oracle.py"},
        "policy": str(path), "policy_id": f"0x{pol.policy_id:08x}",
        "oracle": {"episodes": n, "solved": k, "solved_rate": k / n, "solved_ci95": wilson95(k, n)},
    }
    table: list[tuple[str, object]] = [
        ("scenario", f"{len(specs)} maps x {args.episodes}, {args.obstacles} discs + {args.movers} movers"
                     f"{' (not giving way)' if not style.yields else ''}, seed {args.seed}"),
        ("oracle (privileged)", f"n={n} solved {k} ({k / n:.3f}) [{wilson95(k, n)[0]:.3f}, {wilson95(k, n)[1]:.3f}]: "
                                "a lower bound on what the scenario allows"),
    ]
    for c in ctrls:
        r = by[c.name]
        s = summarise(r)
        won = [row["success"] for row in r]
        lost_solvable = sum(1 for w, o in zip(won, solved, strict=True) if not w and o)
        lost_other = sum(1 for w, o in zip(won, solved, strict=True) if not w and not o)
        beyond = sum(1 for w, o in zip(won, solved, strict=True) if w and not o)
        result[c.name] = {**s, "failed_oracle_solved": lost_solvable, "failed_oracle_not": lost_other,
                          "won_oracle_not": beyond}
        lo, hi = s["success_ci95"]
        table.append((c.name, f"success {sum(won)} ({s['success_rate']:.3f}) [{lo:.3f}, {hi:.3f}], collisions "
                              f"{s['outcomes'].get('collision', 0)}; of its {n - sum(won)} failures the oracle "
                              f"solved {lost_solvable}; it won {beyond} the oracle did not"))
    if ctrls:
        any_won = [any(by[c.name][i]["success"] for c in ctrls) for i in range(n)]
        none = sum(1 for w, o in zip(any_won, solved, strict=True) if not w and not o)
        result["any_controller"] = {"success": sum(any_won), "neither_nor_oracle": none}
        table.append(("any controller", f"{sum(any_won)} ({sum(any_won) / n:.3f}); {none} episodes neither "
                                        "a controller nor the oracle finished"))
    result["per_map"] = {}
    for name in specs:
        idx = [i for i, ep in enumerate(eps) if ep.map == name]
        pm = {"episodes": len(idx), "oracle": sum(solved[i] for i in idx),
              **{c.name: sum(by[c.name][i]["success"] for i in idx) for c in ctrls}}
        result["per_map"][name] = pm
        table.append((f"  {name}", ", ".join(f"{key} {v}" for key, v in pm.items())))
    result["episodes"] = rows
    table.append(("campaign", f"{stats.engine}, {stats.workers} workers: {len(jobs)} jobs, "
                              f"{stats.as_dict()['wall_s']:.1f} s wall"))
    report("ceiling", table, result, args.json)
    write_campaign(args.json, {"episodes": stats.as_dict()})
    return 0
