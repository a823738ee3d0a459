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

With `--blocked both` (the blocked-passage episodes of `qnav bench decisions
--blocked both`) "right" is a success, or a "no route" on an episode labelled
without a detour; there the oracle must find no way (a check of the label and
the oracle alike), and a controller's wrong "no route" the oracle solved is
counted. `--budget-scale 3` gives the oracle the most time a controller's
re-routes can reach (a longer detour is in the budget).

`--foresight MM` runs a second oracle beside it, limited to what the robot
could see (`ground_station.lab.nav.foresight`): the same search re-planned as
it drives, knowing only the movers that have come within MM of it in line of
sight (2000: the range sensors' reach), each tracked perfectly from then on.
The gap between the two is what knowing the movers beyond the sensors is worth;
a controller's failures that one solved are the ones a robot could win from its
own sightings.

`--kinematic` runs the oracle once more with a differential-drive robot's moves instead of its
relaxation (`oracle.solve_kinematic`: heading in four axis directions, quarter turns in place and
reversing at the twin's rates): the gap to the oracle is what turning in no time and driving sideways
are worth; each controller is paired with it too.

Prints a table and writes JSON (`--json`): `scenario`, `oracle` and each
controller's summary (as `qnav bench nav`'s, with `right` and the failures
the oracle solved), `per_map` (episodes, right for the oracle and each
controller), and `episodes`: one row per episode (map, index on it, the
oracle's time in s or null, the label, each controller's outcome; with
`--foresight`, `seen` (the limited oracle's summary) and per row `seen` and
`seen_s`: its outcome and time; with `--kinematic`, `kinematic` (its summary, with its turn and
reverse time units) and per row `kinematic_s`).
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
    p.add_argument("--obstacles", type=int, default=None, metavar="K", help="static discs (default 3; 0 with --blocked)")
    p.add_argument("--movers", type=int, default=2, metavar="M", help="movers (default %(default)s)")
    p.add_argument("--no-yield", action="store_true", help="movers do not give way (as bench nav)")
    p.add_argument("--blocked", choices=("both",), default=None,
                   help="blocked-passage episodes, both labels, as bench decisions (--obstacles then defaults to 0); "
                        "on one without a detour the right answer is \"no route\" and the oracle must find no way")
    p.add_argument("--budget-scale", type=float, default=1.0, metavar="S",
                   help="the oracle's budget: S x the episode's (default %(default)s: the budget every controller "
                        "starts with; 3: the most a controller's re-routes extend it to)")
    p.add_argument("--foresight", type=float, default=None, metavar="MM",
                   help="also the oracle limited to the movers the robot has seen within MM in line of sight, "
                        "re-planned as it drives (2000: the range sensors' reach)")
    p.add_argument("--kinematic", action="store_true",
                   help="also the oracle restricted to a differential-drive robot's moves: heading in four axis "
                        "directions, quarter turns in place and reversing at the twin's rates")
    p.add_argument("--episodes", type=int, default=40, help="episodes per map (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="scenario seed (default %(default)s)")
    p.add_argument("--policy", default="policies:sector", metavar="FILE",
                   help="the learnt sector policy (default %(default)s)")
    p.add_argument("--controllers", default=DEFAULT_CONTROLLERS,
                   help="comma-separated, as bench nav's; '' for the oracle alone (default %(default)s)")
    p.add_argument("--batch", type=int, default=20, metavar="N", help="episodes per job (default %(default)s)")
    p.add_argument("--json", metavar="FILE", help="write the result (with per-episode rows) as JSON")
    p.add_argument("--draw", metavar="DIR",
                   help="for each episode the first controller got wrong and the oracle right: DIR/MAP-INDEX.png, "
                        "its drive beside the oracle's way, the movers' walks coloured by time")
    add_engine_arguments(p, "episode batches")
    p.set_defaults(func=run)


def ceiling_job(job: dict) -> list[Any]:
    """One job: the oracle's periods (-1: no way found), the limited oracle's (outcome, period) or a
    controller's rows (`episodes.run_job`)."""
    from ground_station.lab.nav.episodes import run_job

    if job["kind"] not in ("oracle", "seen", "kinematic"):
        return run_job(job)
    from firmware_py import robot_spec
    from ground_station.lab.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, PERIOD_S
    from ground_station.lab.nav.foresight import solve_seen
    from ground_station.lab.nav.oracle import solve, solve_kinematic
    from ground_station.maps import load_map

    maps = {name: load_map(spec) for name, spec in job["maps"].items()}
    r = robot_spec.ROBOT_RADIUS_MM
    if job["kind"] == "kinematic":
        return [solve_kinematic(ep, maps[ep.map], r, BUDGET_BASE, BUDGET_FACTOR, PERIOD_S, job["budget_scale"])
                for ep in job["episodes"]]
    if job["kind"] == "seen":
        return [list(solve_seen(ep, maps[ep.map], r, BUDGET_BASE, BUDGET_FACTOR, PERIOD_S, job["see_mm"],
                                job["budget_scale"])) for ep in job["episodes"]]
    return [solve(ep, maps[ep.map], r, BUDGET_BASE, BUDGET_FACTOR, PERIOD_S, job["budget_scale"])
            for ep in job["episodes"]]


def run(args: argparse.Namespace) -> int:
    from firmware_py.policy import PolicyError, load_policy
    from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec
    from ground_station.errors import CliError
    from ground_station.lab.bench.common import report
    from ground_station.lab.campaign.engines import engine_from_args, write_campaign
    from ground_station.lab.nav.controllers import standard_controllers
    from ground_station.lab.nav.episodes import (
        PERIOD_S,
        answered_right,
        mcnemar_exact,
        summarise,
        wilson95,
    )
    from ground_station.lab.nav.oracle import REVERSE_UNITS, TURN_UNITS, UNIT_PERIODS
    from ground_station.lab.nav.scenario import (
        MOVER_SPEED_MM_S,
        MoverStyle,
        blocked_both,
        episodes,
    )
    from ground_station.maps import MapError, load_map

    if args.obstacles is None:
        args.obstacles = 0 if args.blocked else 3
    if args.obstacles < 0 or args.movers < 0 or args.episodes < 1 or args.batch < 1:
        raise CliError("--obstacles/--movers must be >= 0, --episodes/--batch >= 1")
    if not 0 < args.budget_scale <= 10:
        raise CliError(f"--budget-scale {args.budget_scale}: expected 0 < S <= 10")
    if args.foresight is not None and not 0 < args.foresight <= 100_000:
        raise CliError(f"--foresight {args.foresight:g}: expected 0 < MM <= 100000")
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
    maps = {}
    eps = []
    for spec in args.map:
        try:
            gm = load_map(spec)
            if args.blocked is None:
                eps += episodes(gm, args.episodes, args.seed, args.obstacles, args.movers, movers=style)
            else:
                eps += blocked_both(gm, args.episodes, args.seed, args.obstacles, args.movers, style)
        except (MapError, OSError) as exc:
            if args.blocked is None or not isinstance(exc, MapError):
                raise CliError(str(exc)) from None
            print(f"--blocked both: skipping {exc}")
            continue
        specs[gm.name] = spec
        maps[gm.name] = gm
    if not eps:
        raise CliError("no map has such an episode")
    base = {"policy": str(path), "maps": specs}
    chunks = [eps[i:i + args.batch] for i in range(0, len(eps), args.batch)]
    jobs: list[dict[str, Any]] = [{**base, "kind": "oracle", "controller": "oracle", "episodes": c,
                                   "budget_scale": args.budget_scale} for c in chunks]
    if args.foresight is not None:
        jobs += [{**base, "kind": "seen", "controller": "seen", "episodes": c, "see_mm": args.foresight,
                  "budget_scale": args.budget_scale} for c in chunks]
    if args.kinematic:
        jobs += [{**base, "kind": "kinematic", "controller": "kinematic", "episodes": c,
                  "budget_scale": args.budget_scale} for c in chunks]
    jobs += [{**base, "kind": "twin", "controller": c.name, "episodes": ch} for c in ctrls for ch in chunks]
    with engine_from_args(args) as engine:
        out, stats = engine.map(ceiling_job, jobs, desc="episodes", unit="batch")
    by: dict[str, list] = {}
    for job, res in zip(jobs, out, strict=True):
        by.setdefault(job["controller"], []).extend(res)
    periods = by["oracle"]
    none_label = [ep.blocked is not None and not ep.blocked["detour"] for ep in eps]  # "no route" is right
    solved = [p >= 0 for p in periods]
    # the oracle is right where it found a way, and on an episode labelled without a detour where it found none
    oracle_right = [s != nl for s, nl in zip(solved, none_label, strict=True)]
    seen = by.get("seen")  # --foresight: (outcome, period) each
    seen_right = [(o == "success") != nl for (o, _p), nl in zip(seen, none_label, strict=True)] if seen else None

    kin = by.get("kinematic")  # --kinematic: periods each (-1: no way found)
    kin_right = [(p >= 0) != nl for p, nl in zip(kin, none_label, strict=True)] if kin else None

    won_by = {c.name: [answered_right(row) for row in by[c.name]] for c in ctrls}
    index: dict[str, int] = {}
    rows: list[dict[str, Any]] = []
    for ep, p in zip(eps, periods, strict=True):
        i = index[ep.map] = index.get(ep.map, -1) + 1
        rows.append({"map": ep.map, "index": i, "oracle_s": round(p * PERIOD_S, 2) if p >= 0 else None,
                     **({"detour": bool(ep.blocked["detour"])} if ep.blocked else {}),
                     **({"seen": seen[len(rows)][0], "seen_s": round(seen[len(rows)][1] * PERIOD_S, 2)
                         if seen[len(rows)][0] == "success" else None} if seen else {}),
                     **({"kinematic_s": round(kin[len(rows)] * PERIOD_S, 2) if kin[len(rows)] >= 0 else None}
                        if kin else {}),
                     **{c.name: by[c.name][len(rows)]["outcome"] for c in ctrls}})
    n = len(eps)
    k = sum(oracle_right)
    ci = wilson95(k, n)
    result: dict = {
        "scenario": {"maps": list(specs), "obstacles": args.obstacles, "movers": args.movers,
                     "movers_yield": style.yields, "seed": args.seed, "episodes_per_map": args.episodes,
                     "blocked": args.blocked, "oracle_budget_scale": args.budget_scale,
                     "definition": "ground_station/lab/nav/scenario.py; oracle: ground_station/lab/nav/oracle.py"},
        "policy": str(path), "policy_id": f"0x{pol.policy_id:08x}",
        "oracle": {"episodes": n, "right": k, "right_rate": k / n, "right_ci95": ci, "solved": sum(solved),
                   "found_without_detour": sum(s and nl for s, nl in zip(solved, none_label, strict=True))},
    }
    table: list[tuple[str, object]] = [
        ("scenario", f"{len(specs)} maps x {args.episodes}, {args.obstacles} discs + {args.movers} movers"
                     f"{' (not giving way)' if not style.yields else ''}"
                     f"{', blocked passages (both labels)' if args.blocked else ''}, seed {args.seed}; "
                     f"oracle budget x {args.budget_scale:g}"),
        ("oracle (privileged)", f"n={n} right {k} ({k / n:.3f}) [{ci[0]:.3f}, {ci[1]:.3f}]: a lower bound on "
                                "what the scenario allows"),
    ]
    if seen and seen_right is not None:
        ks = sum(seen_right)
        outs = {o: sum(1 for s_, _p in seen if s_ == o) for o in ("success", "collision", "stand-off", "timeout")}
        both = [(o_p, s_p) for o_p, (o, s_p) in zip(periods, seen, strict=True) if o_p >= 0 and o == "success"]
        result["seen"] = {"see_mm": args.foresight, "episodes": n, "right": ks, "right_rate": ks / n,
                          "right_ci95": wilson95(ks, n), "outcomes": outs,
                          "won_oracle_not": sum(1 for a, b in zip(seen_right, oracle_right, strict=True) if a and not b),
                          "both_finished": len(both), "as_quick_as_oracle": sum(s_p == o_p for o_p, s_p in both)}
        lo, hi = wilson95(ks, n)
        table.append((f"oracle seeing {args.foresight:g} mm", f"n={n} right {ks} ({ks / n:.3f}) [{lo:.3f}, {hi:.3f}], "
                      f"collisions {outs['collision']}, stand-offs {outs['stand-off']}, timeouts "
                      f"{outs['timeout']}: knowing only the movers it has seen; as quick as the oracle in "
                      f"{result['seen']['as_quick_as_oracle']} of the {len(both)} both finished"))
    if kin and kin_right is not None:
        kk = sum(kin_right)
        both_k = [(o_p, k_p) for o_p, k_p in zip(periods, kin, strict=True) if o_p >= 0 and k_p >= 0]
        slower = sorted(k_p / o_p for o_p, k_p in both_k if o_p > 0)
        result["kinematic"] = {"episodes": n, "right": kk, "right_rate": kk / n, "right_ci95": wilson95(kk, n),
                               "turn_units": TURN_UNITS, "reverse_units": REVERSE_UNITS,
                               "won_oracle_not": sum(1 for a, b in zip(kin_right, oracle_right, strict=True)
                                                     if a and not b),
                               "both_finished": len(both_k),
                               "time_over_oracle_median": slower[len(slower) // 2] if slower else None}
        lo, hi = wilson95(kk, n)
        ratio = f"{slower[len(slower) // 2]:.2f}" if slower else "-"
        table.append(("oracle, robot's moves", f"n={n} right {kk} ({kk / n:.3f}) [{lo:.3f}, {hi:.3f}]: heading in "
                      f"4 axis directions, quarter turns in place ({TURN_UNITS * UNIT_PERIODS * PERIOD_S:g} s), "
                      f"reversing ({REVERSE_UNITS * UNIT_PERIODS * PERIOD_S:g} s a step); median time "
                      f"{ratio} x the oracle's where both finished ({len(both_k)})"))
    if any(none_label):
        table.append(("  without a detour", f"the oracle found a way in {result['oracle']['found_without_detour']} "
                                            f"of {sum(none_label)} (the label says none: 0 expected)"))
    for c in ctrls:
        r = by[c.name]
        s = summarise(r)
        won = won_by[c.name]
        lost_solvable = sum(1 for w, o in zip(won, oracle_right, strict=True) if not w and o)
        wrong_no_route = sum(1 for w, o, row in zip(won, oracle_right, r, strict=True)
                             if not w and o and row["outcome"] == "no_route")
        beyond = sum(1 for w, o in zip(won, oracle_right, strict=True) if w and not o)
        result[c.name] = {**s, "right": sum(won), "failed_oracle_solved": lost_solvable,
                          "failed_oracle_not": n - sum(won) - lost_solvable,
                          "no_route_oracle_solved": wrong_no_route, "won_oracle_not": beyond}
        by_seen = ""
        if seen_right is not None:
            paired = mcnemar_exact([{"success": w} for w in won], [{"success": o} for o in seen_right])
            result[c.name]["failed_seen_solved"] = paired["b_only"]
            result[c.name]["paired_with_seen"] = paired
            by_seen = (f", the oracle seeing {args.foresight:g} mm {paired['b_only']} (paired: {paired['a_only']} vs "
                       f"{paired['b_only']}, p = {paired['p_exact']:.2g})")
        if kin_right is not None:
            paired = mcnemar_exact([{"success": w} for w in won], [{"success": o} for o in kin_right])
            result[c.name]["paired_with_kinematic"] = paired
            by_seen += (f", the robot's-moves oracle {paired['b_only']} (paired: {paired['a_only']} vs "
                        f"{paired['b_only']}, p = {paired['p_exact']:.2g})")
        lo, hi = wilson95(sum(won), n)
        table.append((c.name, f"right {sum(won)} ({sum(won) / n:.3f}) [{lo:.3f}, {hi:.3f}], collisions "
                              f"{s['outcomes'].get('collision', 0)}; of its {n - sum(won)} failures the oracle "
                              f"solved {lost_solvable} ({wrong_no_route} a \"no route\"){by_seen}; it won {beyond} "
                              "the oracle did not"))
    if ctrls:
        any_won = [any(won_by[c.name][i] for c in ctrls) for i in range(n)]
        neither = sum(1 for w, o in zip(any_won, oracle_right, strict=True) if not w and not o)
        result["any_controller"] = {"right": sum(any_won), "neither_nor_oracle": neither}
        table.append(("any controller", f"{sum(any_won)} ({sum(any_won) / n:.3f}); {neither} episodes neither "
                                        "a controller nor the oracle got right"))
    result["per_map"] = {}
    for name in specs:
        idx = [i for i, ep in enumerate(eps) if ep.map == name]
        pm = {"episodes": len(idx), "oracle": sum(oracle_right[i] for i in idx),
              **({"seen": sum(seen_right[i] for i in idx)} if seen_right is not None else {}),
              **({"kinematic": sum(kin_right[i] for i in idx)} if kin_right is not None else {}),
              **{c.name: sum(won_by[c.name][i] for i in idx) for c in ctrls}}
        result["per_map"][name] = pm
        table.append((f"  {name}", ", ".join(f"{key} {v}" for key, v in pm.items())))
    result["episodes"] = rows
    table.append(("campaign", f"{stats.engine}, {stats.workers} workers: {len(jobs)} jobs, "
                              f"{stats.as_dict()['wall_s']:.1f} s wall"))
    if args.draw and ctrls:
        _draw_all(args.draw, eps, rows, maps, ctrls[0], won_by[ctrls[0].name], oracle_right)
    report("ceiling", table, result, args.json)
    write_campaign(args.json, {"episodes": stats.as_dict()})
    return 0


def _draw_all(folder: str, eps: list, rows: list[dict], maps: dict, ctrl: Any, won: list[bool],
              oracle_right: list[bool]) -> None:
    """--draw: one PNG per episode `ctrl` got wrong and the oracle right (module docstring)."""
    from pathlib import Path

    from firmware_py.atomic import atomic_write

    todo = [i for i in range(len(eps)) if not won[i] and oracle_right[i]]
    for i in todo:
        out = Path(folder) / f"{rows[i]['map']}-{rows[i]['index']}.png"
        atomic_write(out, draw(eps[i], maps[eps[i].map], ctrl, rows[i]), make_parents=True)
    print(f"drew {len(todo)} episodes in {folder}")


def draw(ep: Any, gm: Any, ctrl: Any, row: dict) -> bytes:
    """PNG: `ctrl`'s drive of `ep` on the twin (left) beside the oracle's way (right), over the map, the
    discs, the waypoints and the movers' walks (coloured by time: what the oracle plans against)."""
    import numpy as np

    from firmware_py import robot_spec
    from ground_station.lab.nav import planned
    from ground_station.lab.nav.episodes import (
        BUDGET_BASE,
        BUDGET_FACTOR,
        OUTCOMES,
        PERIOD_S,
        STALL_STEPS,
    )
    from ground_station.lab.nav.oracle import mover_tracks, solve_path
    from ground_station.lab.nav.scenario import rollout_arrays
    from ground_station.plotting import png_bytes, pyplot

    drive: list[tuple[float, float]] = []
    outcome, *_ = planned.rollout(ep, gm, ctrl, BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS,
                                  watch=lambda x, y, _m: drive.append((x, y)))
    period, way = solve_path(ep, gm, robot_spec.ROBOT_RADIUS_MM, BUDGET_BASE, BUDGET_FACTOR, PERIOD_S)
    discs, movers, wps, _, _ = rollout_arrays(ep, True)
    cell = gm.cell_size_m * 1000.0
    span = max(len(drive), period, 1)
    walks = mover_tracks(movers, np.ascontiguousarray(gm.occ, dtype=np.uint8), cell, discs, span, PERIOD_S)
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(13, 6.5))
    h, w = gm.occ.shape
    titles = (f"{ctrl.name}: {OUTCOMES[outcome]} after {len(drive) * PERIOD_S:.0f} s",
              f"oracle: the goal at {period * PERIOD_S:.0f} s")
    for ax, title in zip(axes, titles, strict=True):
        ax.imshow(gm.occ, cmap="Greys", extent=(0, w * cell, 0, h * cell), origin="upper")
        for dx, dy, r in discs:
            ax.add_patch(plt.Circle((dx, dy), r, color="saddlebrown"))
        for k in range(walks.shape[1]):
            ax.scatter(walks[:span:10, k, 0], walks[:span:10, k, 1], c=np.arange(0, span, 10) * PERIOD_S,
                       cmap="autumn", s=3, vmin=0, vmax=span * PERIOD_S)
        ax.plot(wps[:, 0], wps[:, 1], "g+--", ms=9, lw=0.8)
        ax.plot(ep.start[0], ep.start[1], "go", ms=7)
        ax.set_title(title)
        ax.set_aspect("equal")
    if drive:
        d = np.asarray(drive)
        axes[0].scatter(d[:, 0], d[:, 1], c=np.arange(len(d)) * PERIOD_S, cmap="winter", s=2, vmin=0,
                        vmax=span * PERIOD_S)
    if way:
        o = np.asarray(way)
        axes[1].scatter(o[:, 1], o[:, 2], c=o[:, 0] * PERIOD_S, cmap="winter", s=4, vmin=0, vmax=span * PERIOD_S)
    fig.suptitle(f"{row['map']} episode {row['index']}: the robot (blue) and the movers (red to yellow), "
                 "colour = time")
    return png_bytes(fig, dpi=70)
