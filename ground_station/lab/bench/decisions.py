"""`qnav bench decisions`: which recovery decision ends each failed twin
episode (issue 47).

The episodes are `qnav bench nav`'s (the same seeded scenario for the same
options); each controller on the robot's local planner drives them on the
twin with its tick side traced (`ground_station.lab.nav.decisions`): every
failure is counted under the decision that ended it: `declared:still` /
`declared:cap` ("no route" after max_rounds still rounds / after the rounds'
cap; `+gave_way` when it stood aside first), or a timeout, loop or collision
with where its last 400 periods went (`waiting`, `giving_way`,
`backing_off`, `detour`: a whole-map route, `local`: the table, guard and
monitor on the window's sub-goals). With `--blocked`, a "no route" on an
episode without a detour is the right answer and is not a failure. Failures
that end in a stand-off are counted too: a mover's body nearer than 60 mm to
the robot's for 90 % of the last 10 s (a mover that does not give way
stands while a step would overlap the robot), and how many of those had two
movers that near, the robot pinned between them. So are the wrong "no route"
whose last whole-map search would have found a route to a later waypoint
(the next two or the goal) over the same memory: what a skip of the
unreachable waypoint would reach.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("decisions", help="which recovery decision ends each failed twin episode",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--map", action="append", metavar="NAME|PATH", required=True, help="map (repeatable)")
    p.add_argument("--obstacles", type=int, default=None, metavar="K", help="static discs (default 3; 0 with --blocked)")
    p.add_argument("--movers", type=int, default=2, metavar="M", help="movers (default %(default)s)")
    p.add_argument("--no-yield", action="store_true", help="movers do not give way (as bench nav)")
    p.add_argument("--blocked", choices=("both",), default=None, help="blocked-passage episodes, both labels")
    p.add_argument("--episodes", type=int, default=40, help="episodes per map (default %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--policy", default="policies:sector", metavar="FILE")
    p.add_argument("--controllers", default="learnt", help="comma-separated, on the local planner (default learnt)")
    p.add_argument("--json", metavar="FILE", help="per-episode rows")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from firmware_py.policy import load_policy
    from firmware_py.shipped_policies import resolve_policy_spec
    from ground_station.errors import CliError
    from ground_station.lab.nav.controllers import standard_controllers
    from ground_station.lab.nav.decisions import trace
    from ground_station.lab.nav.episodes import answered_right
    from ground_station.lab.nav.scenario import (
        MOVER_SPEED_MM_S,
        MoverStyle,
        blocked_both,
        episodes,
    )
    from ground_station.maps import MapError, load_map

    pol = load_policy(str(resolve_policy_spec(args.policy)))
    try:
        ctrls = standard_controllers(pol, tuple(c.strip() for c in args.controllers.split(",") if c.strip()))
    except ValueError as exc:
        raise CliError(f"--controllers: {exc}") from None
    if any(c.local is None for c in ctrls):
        raise CliError("bench decisions traces controllers on the local planner (learnt, learnt_rules, seek_local, "
                       "vfh_local) of a policy that carries one")
    style = MoverStyle(speed=MOVER_SPEED_MM_S, yields=not args.no_yield)
    k = args.obstacles if args.obstacles is not None else (0 if args.blocked else 3)
    eps, maps = [], {}
    for spec in args.map:
        gm = load_map(spec)
        maps[gm.name] = gm
        if args.blocked is None:
            eps += episodes(gm, args.episodes, args.seed, k, args.movers, movers=style)
            continue
        try:
            eps += blocked_both(gm, args.episodes, args.seed, k, args.movers, style)
        except MapError as exc:
            print(f"--blocked both: skipping {exc}")
    out = {}
    for c in ctrls:
        rows = trace(eps, maps, c)
        right = [answered_right(r) for r in rows]
        fails = Counter(r["decision"] + (":no_detour" if r.get("blocked", {}).get("detour") is False else "")
                        for r, ok in zip(rows, right, strict=True) if not ok)
        stands = sum(r["standoff"] for r, ok in zip(rows, right, strict=True) if not ok)
        pinned = sum(r["sandwich"] for r, ok in zip(rows, right, strict=True) if not ok)
        wrong = [r for r, ok in zip(rows, right, strict=True) if not ok and r["outcome"] == "no_route"]
        print(f"{c.name:13s} n={len(rows)} right {sum(right)} ({sum(right) / max(1, len(rows)):.3f}); failures "
              f"{sum(fails.values())}: " + ", ".join(f"{k} {v}" for k, v in fails.most_common())
              + f"; {stands} of them end in a stand-off ({pinned} between two movers); "
              f"{sum(bool(r['later_reachable']) for r in wrong)} of {len(wrong)} wrong 'no route' with a later "
              "waypoint reachable")
        out[c.name] = {"episodes": len(rows), "right": sum(right), "failures": dict(fails), "rows": rows}
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"scenario": {"maps": args.map, "seed": args.seed, "episodes": args.episodes, "obstacles": k,
                                    "movers": args.movers, "no_yield": args.no_yield, "blocked": args.blocked},
                       **out}, f)
        print(f"wrote {args.json}")
    return 0
