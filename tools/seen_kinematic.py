"""Issue 47 experiment: the seeing oracle (`qnav bench ceiling --foresight`) with a differential-drive
robot's moves (`qnav bench ceiling --kinematic`'s), on `qnav bench nav`'s episodes.

`ground_station.lab.nav.foresight.solve_seen` re-plans the oracle's search from the movers the robot
has seen; here that search is `oracle.solve_kinematic`'s over (time unit, heading, point), with the way
kept (how each state was first reached), the heading carried from plan to plan, re-plans only between
whole moves (a quarter turn or a step back spans several units), and the back-off along the heading
(stay, or 1..4 steps ahead, or back at reverse speed) instead of along any axis. Prints, per map and in
all, the episodes it finishes and how the others end.

    .venv/bin/python tools/seen_kinematic.py maze-12x12-s306 maze-16x16-s304 maze-20x20-s305 --workers 2
"""

from __future__ import annotations

import argparse
import json
import math
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from ground_station.lab.nav import oracle
from ground_station.lab.nav.decisions import STANDOFF_GAP_MM
from ground_station.lab.nav.foresight import (
    BACK_OFF_STEPS,
    BACK_OFF_UNITS,
    LEG_SLACK_UNITS,
    REPLAN_UNITS,
    _body_gap,
    look,
    seen_tracks,
)
from ground_station.lab.nav.obstacle_twin import hits_discs, step_movers
from ground_station.lab.nav.oracle import (
    LATTICE_MM,
    REVERSE_UNITS,
    UNIT_PERIODS,
)
from ground_station.lab.nav.planned import budget_periods
from ground_station.lab.nav.scenario import rollout_arrays
from ground_station.learn.sector.kernels import GOAL_TOL_MM
from ground_station.learn.sector.twin import disc_hits

DI, DJ = oracle.HEAD_DI, oracle.HEAD_DJ


def solve_seen_kin(ep: Any, gm: Any, radius_mm: float, budget_base: float, budget_factor: float,
                   period_s: float, see_mm: float) -> tuple[str, int]:
    """foresight.solve_seen with the robot's moves (module docstring): (outcome, period)."""
    discs, movers, wps, remaining, plan_len = rollout_arrays(ep, True)
    occ = np.ascontiguousarray(gm.occ, dtype=np.uint8)
    cell = gm.cell_size_m * 1000.0
    budget = int(budget_periods(plan_len, budget_base, budget_factor))
    unit = UNIT_PERIODS
    x0, y0, th = ep.start
    hd = oracle.axis_heading(th)
    lattice = oracle.lattice_of(float(x0), float(y0), occ.shape, cell)
    x, y = float(x0), float(y0)
    k = t = since = 0
    seen = {}
    plan = []
    at_boundary = True
    no_discs = np.zeros((0, 3))
    while t + unit <= budget:
        new = look(occ, cell, discs, x, y, movers, see_mm, t, seen)
        if at_boundary and (new or since >= REPLAN_UNITS or not plan):
            known, units, tracks = seen_tracks(occ, cell, discs, seen, t, x, y, wps[k], remaining[k], budget,
                                               period_s)
            way = oracle.kinematic_search_from(occ, cell, radius_mm, discs, tracks, x, y, hd, wps[k:], units, lattice,
                                               leg_slack=LEG_SLACK_UNITS)[1] if units > 0 else []
            plan = way if way else _kback_off(occ, cell, radius_mm, discs, known, x, y, hd, period_s)
            since = 0
        nx_, ny_, nd, at_boundary = plan.pop(0)
        for p in range(1, unit + 1):
            rx, ry = x + (nx_ - x) * p / unit, y + (ny_ - y) * p / unit
            step_movers(movers, occ, cell, discs, rx, ry, float(radius_mm), period_s)
            if hits_discs(rx, ry, float(radius_mm), no_discs, movers):
                return "collision", t + p
        t, since, x, y, hd = t + unit, since + 1, nx_, ny_, nd
        if at_boundary:
            while k < len(wps) and (x - wps[k, 0]) ** 2 + (y - wps[k, 1]) ** 2 <= GOAL_TOL_MM ** 2:
                k += 1
            if k == len(wps):
                return "success", t
    return ("stand-off" if _body_gap(x, y, radius_mm, movers) <= STANDOFF_GAP_MM else "timeout"), t


def _kback_off(occ, cell, radius_mm, discs, known, x, y, hd, period_s):
    """Stay one unit, or drive 1..BACK_OFF_STEPS steps ahead or back along the heading: the way that
    leaves the robot farthest from the nearest known mover BACK_OFF_UNITS after; its first whole move."""
    h, w = occ.shape
    unit = UNIT_PERIODS
    dx, dy = DI[hd] * LATTICE_MM, DJ[hd] * LATTICE_MM
    best, best_gap = [(x, y, hd, True)], -math.inf
    for sign, per_step in ((0, 1), (1, 1), (-1, REVERSE_UNITS)):
        for steps in ([1] if sign == 0 else range(1, BACK_OFF_STEPS + 1)):
            mv = known.copy()
            clear = True
            px, py = x, y
            n = steps * per_step * unit
            for p in range(1, n + 1):
                px, py = x + sign * dx * steps * p / n, y + sign * dy * steps * p / n
                step_movers(mv, occ, cell, discs, px, py, float(radius_mm), period_s)
                if disc_hits(occ, h, w, cell, px, py, radius_mm) or hits_discs(px, py, radius_mm, discs, mv):
                    clear = False
                    break
            if not clear:
                break
            for _ in range(BACK_OFF_UNITS * unit):
                step_movers(mv, occ, cell, discs, px, py, float(radius_mm), period_s)
            gap = _body_gap(px, py, radius_mm, mv)
            if gap > best_gap + 1e-6:
                best_gap = gap
                if sign == 0:
                    best = [(x, y, hd, True)]
                else:  # its first step (a step back takes REVERSE_UNITS units)
                    fx, fy = x + sign * dx, y + sign * dy
                    best = [(x + (fx - x) * u / per_step, y + (fy - y) * u / per_step, hd, u == per_step)
                            for u in range(1, per_step + 1)]
    return best


def _run_map(job: tuple[str, int, int, float]) -> list[str]:
    from firmware_py import robot_spec
    from ground_station.lab.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, PERIOD_S
    from ground_station.lab.nav.scenario import MOVER_SPEED_MM_S, MoverStyle, episodes
    from ground_station.maps import load_map

    name, n, seed, see = job
    gm = load_map(name)
    eps = episodes(gm, n, seed, 6, 3, movers=MoverStyle(speed=MOVER_SPEED_MM_S, yields=False))
    return [solve_seen_kin(ep, gm, robot_spec.ROBOT_RADIUS_MM, BUDGET_BASE, BUDGET_FACTOR, PERIOD_S, see)[0]
            for ep in eps]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("maps", nargs="+", help="built-in map names or .map files (6 discs + 3 non-yielding movers)")
    p.add_argument("--episodes", type=int, default=40, help="episodes per map (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="scenario seed (default %(default)s)")
    p.add_argument("--see", type=float, default=2000.0, metavar="MM", help="sight (default %(default)s mm)")
    p.add_argument("--workers", type=int, default=1, help="processes, one map each (default %(default)s)")
    p.add_argument("--json", type=Path, metavar="FILE", help="write each episode's outcome (map, index, outcome)")
    args = p.parse_args()
    if args.episodes < 1 or args.workers < 1 or not args.see > 0:
        p.error("--episodes and --workers must be >= 1, --see positive")
    jobs = [(m, args.episodes, args.seed, args.see) for m in args.maps]
    with ProcessPoolExecutor(args.workers) as ex:
        results = list(ex.map(_run_map, jobs))
    total: Counter[str] = Counter()
    for name, outs in zip(args.maps, results, strict=True):
        c = Counter(outs)
        total.update(c)
        print(f"{name}: {c['success']} of {len(outs)} ({dict(c)})")
    n = sum(total.values())
    print(f"all: {total['success']} of {n} ({dict(total)}), seeing {args.see:g} mm, seed {args.seed}")
    if args.json is not None:
        rows = [{"map": name, "index": i, "outcome": out}
                for name, outs in zip(args.maps, results, strict=True) for i, out in enumerate(outs)]
        args.json.write_text(json.dumps({"see_mm": args.see, "seed": args.seed, "episodes": rows}, indent=1))


if __name__ == "__main__":
    main()
