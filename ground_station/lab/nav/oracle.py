"""A privileged planner: which scenario episodes could a robot finish at all? (issue 47)

The bench's controllers see discs and movers only through their range
sensors. The oracle here knows them all in advance: the map, every disc and
each mover's whole walk (the movers' own model, `sim_bridge.obstacles.step_movers`,
run ahead), and searches space and time for a way from the start through the
episode's waypoints (each within the controller's `GOAL_TOL_MM`, in order, as
`kernels.pass_waypoints` counts them) to the goal within the episode's period
budget (`planned.budget_periods` of the planned length, the budget every
controller starts with). What it finds is a lower bound on what the scenario
allows: an episode it solves is one a robot that knew the future could finish.

The search (`_search`, numba): the robot's centre on a lattice of
`LATTICE_MM` through its start, time in units of `UNIT_PERIODS` control
periods; per unit it stays, or moves one lattice step along an axis (100 mm in
five 50 ms periods: the twin's full forward speed, 20 mm a period; a
diagonal takes two units, slower than the robot). Every period of a step keeps
the robot's disc clear of the map's cells (`twin.disc_hits`) and the discs, and
at least `MOVER_MARGIN_MM` clear of every mover before and after the movers'
step (while it moves, 40 mm more: it is counted at the lattice point it is
nearer). The margin exceeds a step of the fastest mover, so a mover never
comes within a step of the robot and none ever stands for it: their walks do
not depend on the robot, are computed once (`mover_tracks`), and the search over
(lattice point, time) is exact for them.

Relaxations and restrictions, so read a figure as what they allow: the
oracle turns on the spot in no time and drives sideways (a differential-drive
robot cannot); it never uses a mover's standing for it (a non-yielding mover
stands while a step would overlap the robot: blocking one on purpose is not
searched), keeps `MOVER_MARGIN_MM` from movers, moves only on the lattice and
counts a waypoint only at lattice points. So an episode it does not solve may
still be solvable; one it solves needs a robot as quick to turn.
"""

from __future__ import annotations

import math

import numpy as np

from ground_station.jitcache import numba
from ground_station.lab.nav.obstacle_twin import hits_discs, step_movers
from ground_station.lab.nav.planned import budget_periods
from ground_station.lab.nav.scenario import Episode, rollout_arrays
from ground_station.learn.sector.kernels import FWD_MM_PER_PERIOD, GOAL_TOL_MM
from ground_station.learn.sector.twin import disc_hits
from ground_station.maps import GridMap

LATTICE_MM = 100.0
UNIT_PERIODS = 5  # one lattice step along an axis at full forward speed (FWD_MM_PER_PERIOD a period)
assert LATTICE_MM == UNIT_PERIODS * FWD_MM_PER_PERIOD
MOVER_MARGIN_MM = 35.0  # more than the fastest mover's step in one period (600 mm/s x 50 ms)
FAR_MM = -1.0e9  # where the robot is for the movers' walk: nowhere near (none stands for it)

def mover_tracks(movers: np.ndarray, occ: np.ndarray, cell_mm: float, discs: np.ndarray, periods: int,
                 period_s: float) -> np.ndarray:
    """(periods + 1, M, 3) float64: each mover's (x, y, r) after 0 .. periods steps of the movers'
    model with the robot nowhere near (the walk every mover takes while the robot keeps clear)."""
    m = movers.copy()
    out = np.zeros((periods + 1, m.shape[0], 3))
    out[0] = m[:, [0, 1, 4]]
    for t in range(1, periods + 1):
        step_movers(m, occ, cell_mm, discs, FAR_MM, FAR_MM, 0.0, period_s)
        out[t] = m[:, [0, 1, 4]]
    return out


@numba.njit(cache=True)
def _clear(x, y, clearance, tracks, t0, t1) -> bool:
    """Whether (x, y) stays `clearance` + each mover's radius from every mover at periods t0 .. t1."""
    for t in range(t0, t1 + 1):
        for k in range(tracks.shape[1]):
            d = clearance + tracks[t, k, 2]
            if (x - tracks[t, k, 0]) ** 2 + (y - tracks[t, k, 1]) ** 2 < d * d:
                return False
    return True


@numba.njit(cache=True)
def _search(occ, cell, radius, discs, tracks, x0, y0, lattice, unit, wps, tol, margin):
    """Earliest period the goal (the last of wps) is reached, or -1 (module docstring).

    A step from A to B in time unit t: the robot is within lattice / 2 - step of A in its first
    half and of B in its second, so A clear of the movers (by margin + that) over the first half's
    periods and B over the second's make every period of the step clear (`depart`, `arrive`); a stay
    is checked at the point itself (`stay`). One leg per waypoint: reach[t, j, i] marks lattice point
    (i, j) reachable at time unit t on the current leg; a point within tol of the leg's waypoint ends
    the leg there and then (pass_waypoints advances at once) and starts the next."""
    h, w = occ.shape
    nodisc = np.zeros((0, 5))
    ox = x0 - math.floor(x0 / lattice) * lattice
    oy = y0 - math.floor(y0 / lattice) * lattice
    nx = int((w * cell - ox) / lattice) + 1
    ny = int((h * cell - oy) / lattice) + 1
    units = (tracks.shape[0] - 1) // unit
    half = unit // 2  # periods 1 .. half near A, half + 1 .. unit near B
    slack = lattice * half / unit  # the farthest the robot is from the point it is counted at
    free = np.zeros((ny, nx), dtype=np.bool_)
    for j in range(ny):
        for i in range(nx):
            x = ox + i * lattice
            y = oy + j * lattice
            free[j, i] = not disc_hits(occ, h, w, cell, x, y, radius) and not hits_discs(x, y, radius, discs, nodisc)
    # axis steps clear of the map and the discs at each period on the way: +x, +y (the reverse is the same)
    step_ok = np.zeros((ny, nx, 2), dtype=np.bool_)
    for j in range(ny):
        for i in range(nx):
            for m in range(2):
                i2, j2 = i + 1 - m, j + m
                if i2 >= nx or j2 >= ny or not free[j, i] or not free[j2, i2]:
                    continue
                good = True
                for p in range(1, unit):
                    x = ox + (i + p / unit * (1 - m)) * lattice
                    y = oy + (j + p / unit * m) * lattice
                    if disc_hits(occ, h, w, cell, x, y, radius) or hits_discs(x, y, radius, discs, nodisc):
                        good = False
                        break
                step_ok[j, i, m] = good
    stay = np.zeros((units, ny, nx), dtype=np.bool_)
    depart = np.zeros((units, ny, nx), dtype=np.bool_)
    arrive = np.zeros((units, ny, nx), dtype=np.bool_)
    for t in range(units):
        a = t * unit
        for j in range(ny):
            for i in range(nx):
                if not free[j, i]:
                    continue
                x = ox + i * lattice
                y = oy + j * lattice
                stay[t, j, i] = _clear(x, y, radius + margin, tracks, a, a + unit)
                depart[t, j, i] = _clear(x, y, radius + margin + slack, tracks, a, a + half)
                arrive[t, j, i] = _clear(x, y, radius + margin + slack, tracks, a + half, a + unit)
    i0 = int(round((x0 - ox) / lattice))
    j0 = int(round((y0 - oy) / lattice))
    if not free[j0, i0] or not _clear(x0, y0, radius + margin, tracks, 0, 0):
        return -1
    reach = np.zeros((units + 1, ny, nx), dtype=np.bool_)
    nxt = np.zeros((units + 1, ny, nx), dtype=np.bool_)
    reach[0, j0, i0] = True
    nwp = wps.shape[0]
    for k in range(nwp):
        wx, wy = wps[k, 0], wps[k, 1]
        nxt[:] = False
        found = False
        for t in range(units + 1):
            for j in range(ny):
                for i in range(nx):
                    if not reach[t, j, i]:
                        continue
                    x = ox + i * lattice
                    y = oy + j * lattice
                    if (x - wx) ** 2 + (y - wy) ** 2 <= tol * tol:
                        if k == nwp - 1:
                            return t * unit
                        nxt[t, j, i] = True  # the next leg starts here, now
                        found = True
                        continue
                    if t == units:
                        continue
                    if stay[t, j, i]:
                        reach[t + 1, j, i] = True
                    if not depart[t, j, i]:
                        continue
                    if i + 1 < nx and step_ok[j, i, 0] and arrive[t, j, i + 1]:
                        reach[t + 1, j, i + 1] = True
                    if i > 0 and step_ok[j, i - 1, 0] and arrive[t, j, i - 1]:
                        reach[t + 1, j, i - 1] = True
                    if j + 1 < ny and step_ok[j, i, 1] and arrive[t, j + 1, i]:
                        reach[t + 1, j + 1, i] = True
                    if j > 0 and step_ok[j - 1, i, 1] and arrive[t, j - 1, i]:
                        reach[t + 1, j - 1, i] = True
        if not found:
            return -1
        reach[:] = nxt
    return -1


def solve(ep: Episode, gm: GridMap, radius_mm: float, budget_base: float, budget_factor: float,
          period_s: float) -> int:
    """The earliest period the oracle reaches `ep`'s goal through its waypoints within the episode's
    budget, or -1 if its search finds no way (module docstring)."""
    discs, movers, wps, _, plan_len = rollout_arrays(ep, True)
    occ = np.ascontiguousarray(gm.occ, dtype=np.uint8)
    cell = gm.cell_size_m * 1000.0
    budget = int(budget_periods(plan_len, budget_base, budget_factor))
    tracks = mover_tracks(movers, occ, cell, discs, budget, period_s)
    x0, y0, _ = ep.start
    return int(_search(occ, cell, float(radius_mm), discs, tracks, float(x0), float(y0), LATTICE_MM, UNIT_PERIODS,
                       np.ascontiguousarray(wps), float(GOAL_TOL_MM), MOVER_MARGIN_MM))
