"""The oracle limited to what the robot could see: which episodes a planner that knew only the movers
in its sensors' reach could finish (issue 47).

`oracle.solve` knows every mover's whole walk from the start. Here the same space-time search
(`oracle.search_from`) is re-planned as the robot goes, from what it has seen by then: a mover is
seen while its centre is within `see_mm` (+ its radius) of the robot's, with a clear line of sight
(no map cell or disc on the segment between the centres); once seen it is known for ever after,
predicted from its last sighting with the movers' own model (`sim_bridge.obstacles.step_movers`, the
robot far away). So this is a tracker that never loses a mover and knows each one's speed and
bounces exactly; what it lacks is the movers it has not seen yet: one coming round a corner or out
of a side corridor is planned with from the moment it shows.

The robot drives the plan one lattice step (a time unit, `oracle.UNIT_PERIODS` periods) at a time
against the true movers, stepped with the robot where it is (as the twin steps them: one that does
not give way stands while a step would overlap the robot); it re-plans every `REPLAN_UNITS` units,
at once when a mover it had not seen shows, and after the plan runs out. Where the search finds no
way with what it knows (its ways keep clear of every mover, so a mover that does not give way and
stands at the robot, its step overlapping the robot, leaves none) it backs off one unit (`_back_off`:
out of the movers' way, judged 2 s on) and searches again. A robot's disc touching a mover's is a
collision and ends the episode; the goal within the budget a success; else a timeout, or a
stand-off where a mover's body stands within `decisions.STANDOFF_GAP_MM` of the robot's at the end
(pinned where it cannot back off, as in a dead end).

It keeps the oracle's relaxations (turns in no time, drives sideways, on the lattice) and its
keep-clear margins, and bounds the search's work: each search looks at most twice the route left
(at full speed) + 30 s ahead, and continues from arrivals at a waypoint within `LEG_SLACK_UNITS` of
the first (`oracle._search`). So a figure here is what such a planner allows, not a bound on a
controller: the search never uses a mover's standing for the robot (a controller that drives at
movers that do not give way can be quicker, and the bench's controllers win some episodes it does
not), one that turns and sees less does worse.
"""

from __future__ import annotations

import math

import numpy as np

from ground_station.jitcache import numba
from ground_station.lab.nav import oracle
from ground_station.lab.nav.decisions import STANDOFF_GAP_MM
from ground_station.lab.nav.obstacle_twin import hits_discs, step_movers
from ground_station.lab.nav.planned import budget_periods
from ground_station.lab.nav.scenario import Episode, rollout_arrays
from ground_station.learn.sector.kernels import GOAL_TOL_MM
from ground_station.learn.sector.twin import disc_hits
from ground_station.maps import GridMap

REPLAN_UNITS = 4  # 1 s at 50 ms periods: the robot's planner worker re-plans about as often
LEG_SLACK_UNITS = 40  # 10 s: later arrivals at a waypoint are not searched on from
HORIZON_SLACK_UNITS = 120  # 30 s beyond twice the route left at full speed
BACK_OFF_UNITS = 8  # 2 s: how long after its way out a back-off is judged
BACK_OFF_STEPS = 4  # the longest way out looked at: 400 mm, more than a body's width aside
SIGHT_STEP_MM = 20.0  # the line of sight is sampled this often (under half the thinnest wall cell)


@numba.njit(cache=True)
def sees(occ, cell, discs, rx, ry, mx, my, reach_mm) -> bool:
    """Whether a robot at (rx, ry) sees a mover centred at (mx, my): within `reach_mm` and no map
    cell or disc on the segment between the centres (sampled every SIGHT_STEP_MM)."""
    d = math.hypot(mx - rx, my - ry)
    if d > reach_mm:
        return False
    h, w = occ.shape
    top = h * cell
    n = int(d / SIGHT_STEP_MM) + 1
    for s in range(1, n):
        x = rx + (mx - rx) * s / n
        y = ry + (my - ry) * s / n
        c = int(math.floor(x / cell))
        r = int(math.floor((top - y) / cell))
        if 0 <= r < h and 0 <= c < w and occ[r, c]:
            return False
        for k in range(discs.shape[0]):
            if (x - discs[k, 0]) ** 2 + (y - discs[k, 1]) ** 2 < discs[k, 2] ** 2:
                return False
    return True


def solve_seen(ep: Episode, gm: GridMap, radius_mm: float, budget_base: float, budget_factor: float,
               period_s: float, see_mm: float, budget_scale: float = 1.0) -> tuple[str, int]:
    """Drive `ep` re-planning from what the robot has seen (module docstring): ("success", the period
    the goal was reached), ("collision", the period of contact), or ("stand-off" or "timeout", the
    budget)."""
    discs, movers, wps, remaining, plan_len = rollout_arrays(ep, True)
    occ = np.ascontiguousarray(gm.occ, dtype=np.uint8)
    cell = gm.cell_size_m * 1000.0
    budget = int(budget_scale * budget_periods(plan_len, budget_base, budget_factor))
    unit = oracle.UNIT_PERIODS
    x0, y0, _ = ep.start
    lattice = oracle.lattice_of(float(x0), float(y0), occ.shape, cell)
    x, y = float(x0), float(y0)  # a lattice point (the lattice runs through the start)
    k = t = since = 0  # the waypoint next, the period, units since the last search
    seen: dict[int, tuple[int, np.ndarray]] = {}  # mover -> (period of its last sighting, its state then)
    plan: list[tuple[float, float]] = []
    no_discs = np.zeros((0, 3))  # contact with the movers only (the plan keeps clear of the discs)
    while t + unit <= budget:
        new = look(occ, cell, discs, x, y, movers, see_mm, t, seen)
        if new or since >= REPLAN_UNITS or not plan:
            plan = _plan(occ, cell, radius_mm, discs, seen, t, x, y, wps[k:], remaining[k], budget, lattice,
                         period_s)
            since = 0
        nx, ny = plan.pop(0)
        for p in range(1, unit + 1):
            rx, ry = x + (nx - x) * p / unit, y + (ny - y) * p / unit
            step_movers(movers, occ, cell, discs, rx, ry, float(radius_mm), period_s)
            if hits_discs(rx, ry, float(radius_mm), no_discs, movers):
                return "collision", t + p
        t, since, x, y = t + unit, since + 1, nx, ny
        while k < len(wps) and (x - wps[k, 0]) ** 2 + (y - wps[k, 1]) ** 2 <= GOAL_TOL_MM ** 2:
            k += 1  # as the search counts them: at lattice points, at once
        if k == len(wps):
            return "success", t
    return ("stand-off" if _body_gap(x, y, radius_mm, movers) <= STANDOFF_GAP_MM else "timeout"), t


def look(occ: np.ndarray, cell: float, discs: np.ndarray, x: float, y: float, movers: np.ndarray, see_mm: float,
         t: int, seen: dict) -> bool:
    """Note in `seen` (mover -> (period, its state then)) each mover the robot at (x, y) sees at period t;
    whether one of them is seen for the first time."""
    new = False
    for m in range(movers.shape[0]):
        if sees(occ, cell, discs, x, y, movers[m, 0], movers[m, 1], see_mm + movers[m, 4]):
            new = new or m not in seen
            seen[m] = (t, movers[m].copy())
    return new


def _body_gap(x: float, y: float, radius_mm: float, movers: np.ndarray) -> float:
    """The gap between a robot's body at (x, y) and the nearest mover's (inf with none)."""
    return min((math.hypot(x - m[0], y - m[1]) - m[4] - radius_mm for m in movers), default=math.inf)


def _plan(occ: np.ndarray, cell: float, radius_mm: float, discs: np.ndarray, seen: dict, t: int, x: float,
          y: float, wps: np.ndarray, after_mm: float, budget: int, lattice: tuple, period_s: float) -> list:
    """The next lattice points, one per time unit: the search's way from (x, y) at period t with the
    movers seen so far, or the back-off's one (`_back_off`) where it finds none."""
    known, units, tracks = seen_tracks(occ, cell, discs, seen, t, x, y, wps[0], after_mm, budget, period_s)
    period, way = oracle.search_from(occ, cell, radius_mm, discs, tracks, x, y, wps, units, lattice,
                                     leg_slack=LEG_SLACK_UNITS)
    if period < 0 or len(way) < 2:
        return [_back_off(occ, cell, radius_mm, discs, known, x, y, period_s)]
    return [(wx, wy) for _p, wx, wy in way[1:]]


def seen_tracks(occ: np.ndarray, cell: float, discs: np.ndarray, seen: dict, t: int, x: float, y: float,
                waypoint: np.ndarray, after_mm: float, budget: int, period_s: float) -> tuple[np.ndarray, int, np.ndarray]:
    """What a search at period t from (x, y) plans with: the movers seen so far, each walked on from its
    last sighting to now (`known`, rows as `movers`), the horizon in time units (twice the way left,
    `waypoint` then `after_mm`, plus HORIZON_SLACK_UNITS, within the budget), and their tracks over it."""
    known = np.zeros((len(seen), 6))
    for n, (when, state) in enumerate(seen.values()):
        s = state[None, :].copy()
        for _ in range(t - when):  # on from its last sighting, as it walks with the robot far away
            step_movers(s, occ, cell, discs, oracle.FAR_MM, oracle.FAR_MM, 0.0, period_s)
        known[n] = s[0]
    to_go = math.hypot(waypoint[0] - x, waypoint[1] - y) + after_mm
    units = min((budget - t) // oracle.UNIT_PERIODS, int(2 * to_go / oracle.LATTICE_MM) + HORIZON_SLACK_UNITS)
    return known, units, oracle.mover_tracks(known, occ, cell, discs, units * oracle.UNIT_PERIODS, period_s)


def _back_off(occ: np.ndarray, cell: float, radius_mm: float, discs: np.ndarray, known: np.ndarray, x: float,
              y: float, period_s: float) -> tuple[float, float]:
    """Where the robot goes for one time unit when the search finds no way: the first lattice step of
    the way out that leaves it farthest from the nearest mover it knows of: staying, or 1 ..
    `BACK_OFF_STEPS` steps straight along an axis, then waiting to `BACK_OFF_UNITS` units after the
    last; every period clear of the map, the discs and those movers. The movers are stepped with the
    robot where it is: one that does not give way stands while its step would overlap the robot, so
    one standing at the robot walks on once the robot is out of its way (a body's width aside, not
    straight back, where it follows). Then it searches again."""
    h, w = occ.shape
    unit = oracle.UNIT_PERIODS
    best, best_gap = (x, y), -math.inf
    for dx, dy in ((0.0, 0.0), (oracle.LATTICE_MM, 0.0), (-oracle.LATTICE_MM, 0.0), (0.0, oracle.LATTICE_MM),
                   (0.0, -oracle.LATTICE_MM)):
        for steps in ([0] if dx == dy == 0.0 else range(1, BACK_OFF_STEPS + 1)):
            movers = known.copy()
            clear = True
            px, py = x, y
            for p in range(1, steps * unit + 1):
                px, py = x + dx * p / unit, y + dy * p / unit
                step_movers(movers, occ, cell, discs, px, py, float(radius_mm), period_s)
                if disc_hits(occ, h, w, cell, px, py, radius_mm) or hits_discs(px, py, radius_mm, discs, movers):
                    clear = False
                    break
            if not clear:
                break  # farther along this axis is no clearer
            for _ in range(BACK_OFF_UNITS * unit):
                step_movers(movers, occ, cell, discs, px, py, float(radius_mm), period_s)
            gap = _body_gap(px, py, radius_mm, movers)
            if gap > best_gap + 1e-6:  # ties keep the earlier: staying, then the fewer steps
                best, best_gap = (x + dx, y + dy), gap
    return best
