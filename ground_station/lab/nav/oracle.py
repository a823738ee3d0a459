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
diagonal is two such steps, slower than the robot). Every period of a step keeps
the robot's disc clear of the map's cells (`twin.disc_hits`) and the discs, and
clear of every mover before and after the movers' step by `keep_clear_mm`
(while it moves, 40 mm more: it is counted at the lattice point it is
nearer): more than the mover's step in a period, and for a mover that gives
way, more than the margin it keeps from the robot. So no mover ever stands or
turns for the robot: their walks do not depend on it, are computed once
(`mover_tracks`), and the search over (lattice point, time) is exact for them.

Relaxations and restrictions, so read a figure as what they allow: the
oracle turns on the spot in no time and drives sideways (a differential-drive
robot cannot); it never uses a mover's standing for it (a non-yielding mover
stands while a step would overlap the robot: blocking one on purpose is not
searched; nor making one that gives way step aside), keeps `keep_clear_mm`
from movers, moves only on the lattice and counts a waypoint only at lattice
points. So an episode it does not solve may
still be solvable; one it solves needs a robot as quick to turn.

`solve_kinematic` drops the first relaxation: the same search over (time unit, heading, lattice point)
with the heading one of the four axis directions, and per unit a stay, one step ahead, a 90-degree
turn in place (`TURN_UNITS`, at the twin's turn rate) or one step back (`REVERSE_UNITS`, at its
reverse speed), as a differential-drive robot moves on the lattice. Stays and turns keep the robot's
disc where it is (it turns about its centre), so they are checked as stays; a step back checks its
start point over its first unit and its end point over its second (each with the step's slack).
"""

from __future__ import annotations

import math

import numpy as np

from ground_station.jitcache import numba
from ground_station.lab.nav.obstacle_twin import hits_discs, step_movers
from ground_station.lab.nav.planned import budget_periods
from ground_station.lab.nav.scenario import Episode, rollout_arrays
from ground_station.learn.sector.kernels import FWD_MM_PER_PERIOD, GOAL_TOL_MM
from ground_station.learn.sector.twin import ACTION_V_MM_S, ACTION_W_RAD_S, disc_hits
from ground_station.maps import GridMap
from sim_bridge.obstacles import YIELD_MARGIN_MM

LATTICE_MM = 100.0
UNIT_PERIODS = 5  # one lattice step along an axis at full forward speed (FWD_MM_PER_PERIOD a period)
assert LATTICE_MM == UNIT_PERIODS * FWD_MM_PER_PERIOD
STEP_SLACK_MM = 5.0  # kept from a mover beyond its step in one period (keep_clear_mm)
FAR_MM = -1.0e9  # where the robot is for the movers' walk: nowhere near (none stands for it)
# how the search first reached a (leg, time, point) (`solve_path`'s `came`): a stay, a step from the
# point at -x, +x, -y, +y, or the leg's start (the start, or where the previous leg's waypoint was passed)
_STAYED, _FROM_W, _FROM_E, _FROM_S, _FROM_N, _LEG_START = 1, 2, 3, 4, 5, 6
_BACK = {_STAYED: (0, 0), _FROM_W: (0, -1), _FROM_E: (0, 1), _FROM_S: (-1, 0), _FROM_N: (1, 0)}  # (dj, di) back
# solve_kinematic: the twin's turn in place (90 degrees) and reverse (one lattice step), in time units
_PERIOD_S = FWD_MM_PER_PERIOD / float(ACTION_V_MM_S[0])
TURN_UNITS = math.ceil(math.pi / 2 / float(ACTION_W_RAD_S[1]) / _PERIOD_S / UNIT_PERIODS)
REVERSE_UNITS = math.ceil(LATTICE_MM / abs(float(ACTION_V_MM_S[3])) / _PERIOD_S / UNIT_PERIODS)
HEAD_DI = np.array([1, 0, -1, 0], dtype=np.int64)  # heading 0: +x, 1: +y, 2: -x, 3: -y
HEAD_DJ = np.array([0, 1, 0, -1], dtype=np.int64)
# how _kinematic_search first reached a state (its `came`): a stay, a step ahead, a quarter turn left
# (from heading d - 1) or right (from d + 1), a step back; _LEG_START as _search's
_K_STAYED, _K_AHEAD, _K_LEFT, _K_RIGHT, _K_BACK = 1, 2, 3, 4, 5


def keep_clear_mm(mover: np.ndarray, period_s: float) -> float:
    """How far the oracle keeps from a mover (x, y, vx, vy, r, yields) beyond contact: more than its
    step in one period, and for one that gives way, more than the margin it keeps from the robot
    (`sim_bridge.obstacles.YIELD_MARGIN_MM`): so it never stands or turns for the robot."""
    yields = mover.shape[0] < 6 or mover[5] != 0.0
    return math.hypot(mover[2], mover[3]) * period_s + STEP_SLACK_MM + (YIELD_MARGIN_MM if yields else 0.0)


def mover_tracks(movers: np.ndarray, occ: np.ndarray, cell_mm: float, discs: np.ndarray, periods: int,
                 period_s: float) -> np.ndarray:
    """(periods + 1, M, 3) float64: each mover's (x, y) after 0 .. periods steps of the movers' model
    with the robot nowhere near (the walk every mover takes while the robot keeps clear), and the
    distance the robot's disc keeps from its centre (its radius + `keep_clear_mm`)."""
    m = movers.copy()
    out = np.zeros((periods + 1, m.shape[0], 3))
    out[:, :, 2] = [m[k, 4] + keep_clear_mm(m[k], period_s) for k in range(m.shape[0])]
    out[0, :, :2] = m[:, :2]
    for t in range(1, periods + 1):
        step_movers(m, occ, cell_mm, discs, FAR_MM, FAR_MM, 0.0, period_s)
        out[t, :, :2] = m[:, :2]
    return out


@numba.njit(cache=True)
def _clear(x, y, clearance, tracks, t0, t1) -> bool:
    """Whether (x, y) stays `clearance` + each mover's keep-clear radius from every mover at periods
    t0 .. t1."""
    for t in range(t0, t1 + 1):
        for k in range(tracks.shape[1]):
            d = clearance + tracks[t, k, 2]
            if (x - tracks[t, k, 0]) ** 2 + (y - tracks[t, k, 1]) ** 2 < d * d:
                return False
    return True


def lattice_of(x0: float, y0: float, gm_shape: tuple[int, int], cell: float) -> tuple[float, float, int, int]:
    """The lattice through (x0, y0): (x, y) of point (0, 0), points along x and y."""
    h, w = gm_shape
    ox = x0 - math.floor(x0 / LATTICE_MM) * LATTICE_MM
    oy = y0 - math.floor(y0 / LATTICE_MM) * LATTICE_MM
    return ox, oy, int((w * cell - ox) / LATTICE_MM) + 1, int((h * cell - oy) / LATTICE_MM) + 1


@numba.njit(cache=True)
def _search(occ, cell, radius, discs, tracks, x0, y0, lattice, unit, wps, tol, ox, oy, free, step_ok, stay,
            depart, arrive, done, reach, nxt, came, goal, leg_slack):
    """Earliest period the goal (the last of wps) is reached, or -1 (module docstring); the caller
    sizes the arrays (`lattice_of`: ny x nx points, units + 1 time units) and gets them filled.

    A step from A to B in time unit t: the robot is within lattice x half / unit (40 mm) of A in
    its first `half` periods and of B in the rest, so A clear of the movers by that more over the
    first half's periods and B over the rest make every period of the step clear (`depart`,
    `arrive`); a stay is checked at the point itself (`stay`). One leg per waypoint: reach[t, j, i] marks lattice point
    (i, j) reachable at time unit t on the current leg; a point within tol of the leg's waypoint ends
    the leg there and then (pass_waypoints advances at once) and starts the next. With `came` of one
    slice per waypoint, how each state was first reached is kept there (the module's _STAYED ..
    _LEG_START) and `goal` gets the goal's (t, j, i). A time unit's stay/depart/arrive are computed
    when the search first reaches it (`done`). A leg is searched until `leg_slack` units after its
    waypoint was first reached (later arrivals there are not continued from: a re-planning caller's
    bound on the work; `solve_path` without one searches them all)."""
    ny, nx = free.shape
    units = stay.shape[0]
    half = unit // 2  # periods 1 .. half near A, half + 1 .. unit near B
    slack = lattice * half / unit  # the farthest the robot is from the point it is counted at
    _static(occ, cell, radius, discs, lattice, unit, ox, oy, free, step_ok)
    i0 = int(round((x0 - ox) / lattice))
    j0 = int(round((y0 - oy) / lattice))
    if not free[j0, i0] or not _clear(x0, y0, radius, tracks, 0, 0):
        return -1
    nwp = wps.shape[0]
    keep = came.shape[0] == nwp
    _mark(reach, came, keep, 0, 0, j0, i0, _LEG_START)
    for k in range(nwp):
        wx, wy = wps[k, 0], wps[k, 1]
        nxt[:] = False
        first = -1
        for t in range(units + 1):
            if first >= 0 and t > first + leg_slack:
                break
            for j in range(ny):
                for i in range(nx):
                    if not reach[t, j, i]:
                        continue
                    x = ox + i * lattice
                    y = oy + j * lattice
                    if (x - wx) ** 2 + (y - wy) ** 2 <= tol * tol:
                        if k == nwp - 1:
                            goal[0], goal[1], goal[2] = t, j, i
                            return t * unit
                        _mark(nxt, came, keep, k + 1, t, j, i, _LEG_START)  # the next leg starts here, now
                        if first < 0:
                            first = t
                        continue
                    if t == units:
                        continue
                    if not done[t]:
                        _rows(t, radius, tracks, ox, oy, lattice, unit, slack, half, free, stay, depart, arrive)
                        done[t] = True
                    if stay[t, j, i]:
                        _mark(reach, came, keep, k, t + 1, j, i, _STAYED)
                    if not depart[t, j, i]:
                        continue
                    if i + 1 < nx and step_ok[j, i, 0] and arrive[t, j, i + 1]:
                        _mark(reach, came, keep, k, t + 1, j, i + 1, _FROM_W)
                    if i > 0 and step_ok[j, i - 1, 0] and arrive[t, j, i - 1]:
                        _mark(reach, came, keep, k, t + 1, j, i - 1, _FROM_E)
                    if j + 1 < ny and step_ok[j, i, 1] and arrive[t, j + 1, i]:
                        _mark(reach, came, keep, k, t + 1, j + 1, i, _FROM_S)
                    if j > 0 and step_ok[j - 1, i, 1] and arrive[t, j - 1, i]:
                        _mark(reach, came, keep, k, t + 1, j - 1, i, _FROM_N)
        if first < 0:
            return -1
        reach[:] = nxt
    return -1


@numba.njit(cache=True)
def _static(occ, cell, radius, discs, lattice, unit, ox, oy, free, step_ok) -> None:
    """The lattice points clear of the map and the discs (`free`), and the axis steps clear of them at
    each period on the way (`step_ok[j, i, 0]`: to +x, `[..., 1]`: to +y; the reverse is the same)."""
    h, w = occ.shape
    ny, nx = free.shape
    nodisc = np.zeros((0, 5))
    for j in range(ny):
        for i in range(nx):
            x = ox + i * lattice
            y = oy + j * lattice
            free[j, i] = not disc_hits(occ, h, w, cell, x, y, radius) and not hits_discs(x, y, radius, discs, nodisc)
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


@numba.njit(cache=True)
def _rows(t, radius, tracks, ox, oy, lattice, unit, slack, half, free, stay, depart, arrive) -> None:
    """Time unit t's stay, depart and arrive for every free lattice point (`_search`)."""
    ny, nx = free.shape
    a = t * unit
    for j in range(ny):
        for i in range(nx):
            if not free[j, i]:
                continue
            x = ox + i * lattice
            y = oy + j * lattice
            stay[t, j, i] = _clear(x, y, radius, tracks, a, a + unit)
            depart[t, j, i] = _clear(x, y, radius + slack, tracks, a, a + half)
            arrive[t, j, i] = _clear(x, y, radius + slack, tracks, a + half, a + unit)


@numba.njit(cache=True, inline="always")
def _mark(reach, came, keep, k, t, j, i, code) -> None:
    """(t, j, i) reached on leg k; with `keep`, how, the first time (`_search`)."""
    if not reach[t, j, i]:
        reach[t, j, i] = True
        if keep:
            came[k, t, j, i] = code


def solve(ep: Episode, gm: GridMap, radius_mm: float, budget_base: float, budget_factor: float,
          period_s: float, budget_scale: float = 1.0) -> int:
    """The earliest period the oracle reaches `ep`'s goal through its waypoints within the episode's
    budget (times `budget_scale`), or -1 if its search finds no way (module docstring)."""
    return solve_path(ep, gm, radius_mm, budget_base, budget_factor, period_s, budget_scale, path=False)[0]


def _episode(ep: Episode, gm: GridMap, budget_base: float, budget_factor: float, period_s: float,
             budget_scale: float) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, int, np.ndarray]:
    """An episode as the searches take it: (occ, cell mm, discs, waypoints, budget in periods, the
    movers' walks over it: `mover_tracks`)."""
    discs, movers, wps, _, plan_len = rollout_arrays(ep, True)
    occ = np.ascontiguousarray(gm.occ, dtype=np.uint8)
    cell = gm.cell_size_m * 1000.0
    budget = int(budget_scale * budget_periods(plan_len, budget_base, budget_factor))
    return occ, cell, discs, wps, budget, mover_tracks(movers, occ, cell, discs, budget, period_s)


def solve_path(ep: Episode, gm: GridMap, radius_mm: float, budget_base: float, budget_factor: float,
               period_s: float, budget_scale: float = 1.0,
               path: bool = True) -> tuple[int, list[tuple[int, float, float]]]:
    """`solve`, and with `path` the way found: (period, x, y) at every time unit from the start
    (the robot moves straight between them at an even speed), [] when none."""
    occ, cell, discs, wps, budget, tracks = _episode(ep, gm, budget_base, budget_factor, period_s, budget_scale)
    x0, y0, _ = ep.start
    return search_from(occ, cell, radius_mm, discs, tracks, float(x0), float(y0), wps, budget // UNIT_PERIODS,
                       lattice_of(float(x0), float(y0), occ.shape, cell), path)


def search_from(occ: np.ndarray, cell: float, radius_mm: float, discs: np.ndarray, tracks: np.ndarray, x0: float,
                y0: float, wps: np.ndarray, units: int, lattice: tuple[float, float, int, int], path: bool = True,
                leg_slack: int | None = None) -> tuple[int, list[tuple[int, float, float]]]:
    """The search (`_search`) from lattice point (x0, y0) at period 0 of `tracks` (the movers' walks from
    then on, `mover_tracks`) through `wps` in order within `units` time units: (the earliest period the
    last is reached or -1, with `path` the way as `solve_path`'s). `lattice`: `lattice_of`'s (ox, oy, nx,
    ny) of the episode's start; `leg_slack`: `_search`'s (None: every arrival at a waypoint)."""
    ox, oy, nx, ny = lattice
    free = np.zeros((ny, nx), dtype=np.bool_)
    step_ok = np.zeros((ny, nx, 2), dtype=np.bool_)
    stay, depart, arrive = (np.zeros((units, ny, nx), dtype=np.bool_) for _ in range(3))
    done = np.zeros(units, dtype=np.bool_)
    reach, nxt = (np.zeros((units + 1, ny, nx), dtype=np.bool_) for _ in range(2))
    nwp = len(wps)
    came = np.zeros((nwp if path else 0, units + 1, ny, nx), dtype=np.int8)
    goal = np.zeros(3, dtype=np.int64)
    wps = np.ascontiguousarray(wps, dtype=np.float64)
    period = int(_search(occ, cell, float(radius_mm), discs, tracks, x0, y0, LATTICE_MM, UNIT_PERIODS, wps,
                         float(GOAL_TOL_MM), ox, oy, free, step_ok, stay, depart, arrive, done, reach, nxt, came,
                         goal, units + 1 if leg_slack is None else int(leg_slack)))
    if period < 0 or not path:
        return period, []

    k, (t, j, i) = nwp - 1, (int(v) for v in goal)
    back = [(t, j, i)]
    while True:
        how = int(came[k, t, j, i])
        if how == _LEG_START:
            if k == 0:
                break  # the start
            k -= 1  # the previous leg ended here, then: its waypoint passed
            continue
        dj, di = _BACK[how]
        t, j, i = t - 1, j + dj, i + di
        back.append((t, j, i))
    return period, [(t * UNIT_PERIODS, ox + i * LATTICE_MM, oy + j * LATTICE_MM) for t, j, i in reversed(back)]


@numba.njit(cache=True)
def _kinematic_search(occ, cell, radius, discs, tracks, x0, y0, h0, lattice, unit, wps, tol, ox, oy, free,
                      step_ok, stay, depart, arrive, done, reach, nxt, turn_units, rev_units, di, dj, came, goal,
                      leg_slack):
    """`_search` over (time unit, heading, point) with a differential drive's moves (module docstring):
    the earliest period the goal is reached, or -1. With `came` of one slice per waypoint, how each
    state was first reached (_K_STAYED .. _LEG_START) and `goal` the goal's (t, heading, j, i), as
    `_search` keeps its way; `leg_slack` as there."""
    ny, nx = free.shape
    units = stay.shape[0]
    half = unit // 2
    slack = lattice * half / unit
    _static(occ, cell, radius, discs, lattice, unit, ox, oy, free, step_ok)
    i0 = int(round((x0 - ox) / lattice))
    j0 = int(round((y0 - oy) / lattice))
    if i0 < 0 or j0 < 0 or i0 >= nx or j0 >= ny or not free[j0, i0] or not _clear(x0, y0, radius, tracks, 0, 0):
        return -1
    nwp = wps.shape[0]
    keep = came.shape[0] == nwp
    _kmark(reach, came, keep, 0, 0, h0, j0, i0, _LEG_START)
    ahead = max(turn_units, rev_units)
    for k in range(nwp):
        wx, wy = wps[k, 0], wps[k, 1]
        nxt[:] = False
        first = -1
        for t in range(units + 1):
            if first >= 0 and t > first + leg_slack:
                break
            for tt in range(t, min(units, t + ahead)):
                if not done[tt]:
                    _rows(tt, radius, tracks, ox, oy, lattice, unit, slack, half, free, stay, depart, arrive)
                    done[tt] = True
            for d in range(4):
                for j in range(ny):
                    for i in range(nx):
                        if not reach[t, d, j, i]:
                            continue
                        x = ox + i * lattice
                        y = oy + j * lattice
                        if (x - wx) ** 2 + (y - wy) ** 2 <= tol * tol:
                            if k == nwp - 1:
                                goal[0], goal[1], goal[2], goal[3] = t, d, j, i
                                return t * unit
                            # the next leg starts here, now, with this heading
                            _kmark(nxt, came, keep, k + 1, t, d, j, i, _LEG_START)
                            if first < 0:
                                first = t
                            continue
                        if t == units:
                            continue
                        if stay[t, j, i]:
                            _kmark(reach, came, keep, k, t + 1, d, j, i, _K_STAYED)
                        i2, j2 = i + di[d], j + dj[d]  # one step ahead
                        if _step_free(step_ok, j, i, j2, i2) and depart[t, j, i] and arrive[t, j2, i2]:
                            _kmark(reach, came, keep, k, t + 1, d, j2, i2, _K_AHEAD)
                        if t + turn_units <= units:  # a quarter turn in place, either way
                            good = True
                            for u in range(t, t + turn_units):
                                if not stay[u, j, i]:
                                    good = False
                                    break
                            if good:
                                _kmark(reach, came, keep, k, t + turn_units, (d + 1) % 4, j, i, _K_LEFT)
                                _kmark(reach, came, keep, k, t + turn_units, (d + 3) % 4, j, i, _K_RIGHT)
                        i2, j2 = i - di[d], j - dj[d]  # one step back
                        back = t + rev_units - 1  # its last unit, near the point it backs to
                        if (t + rev_units <= units and _step_free(step_ok, j, i, j2, i2) and depart[t, j, i]
                                and arrive[t, j, i] and depart[back, j2, i2] and arrive[back, j2, i2]):
                            _kmark(reach, came, keep, k, t + rev_units, d, j2, i2, _K_BACK)
        if first < 0:
            return -1
        reach[:] = nxt
    return -1


@numba.njit(cache=True, inline="always")
def _kmark(reach, came, keep, k, t, d, j, i, code) -> None:
    """(t, heading d, j, i) reached on leg k; with `keep`, how, the first time (`_kinematic_search`)."""
    if not reach[t, d, j, i]:
        reach[t, d, j, i] = True
        if keep:
            came[k, t, d, j, i] = code


@numba.njit(cache=True, inline="always")
def _step_free(step_ok, j, i, j2, i2) -> bool:
    """Whether the axis step between lattice points (j, i) and (j2, i2) is on the lattice and clear of
    the map and the discs (`step_ok`, either direction)."""
    ny, nx = step_ok.shape[0], step_ok.shape[1]
    if not (0 <= i2 < nx and 0 <= j2 < ny):
        return False
    return step_ok[j, min(i, i2), 0] if j == j2 else step_ok[min(j, j2), i, 1]


def axis_heading(heading_rad: float) -> int:
    """The axis direction (0: +x, 1: +y, 2: -x, 3: -y; HEAD_DI/HEAD_DJ) nearest a heading."""
    return int(round((heading_rad % (2 * math.pi)) / (math.pi / 2))) % 4


def solve_kinematic(ep: Episode, gm: GridMap, radius_mm: float, budget_base: float, budget_factor: float,
                    period_s: float, budget_scale: float = 1.0) -> int:
    """`solve` for a differential-drive robot (module docstring): the earliest period the goal is
    reached through the waypoints within the budget, starting with the axis heading nearest the
    episode's, or -1."""
    occ, cell, discs, wps, budget, tracks = _episode(ep, gm, budget_base, budget_factor, period_s, budget_scale)
    x0, y0, heading = ep.start
    return kinematic_search_from(occ, cell, radius_mm, discs, tracks, float(x0), float(y0), axis_heading(heading),
                                 wps, budget // UNIT_PERIODS, lattice_of(float(x0), float(y0), occ.shape, cell),
                                 path=False)[0]


def kinematic_search_from(occ: np.ndarray, cell: float, radius_mm: float, discs: np.ndarray, tracks: np.ndarray,
                          x0: float, y0: float, h0: int, wps: np.ndarray, units: int,
                          lattice: tuple[float, float, int, int], path: bool = True,
                          leg_slack: int | None = None) -> tuple[int, list[tuple[float, float, int, bool]]]:
    """`search_from` with the robot's moves (`_kinematic_search`), from axis heading `h0`: (the earliest
    period the last waypoint is reached or -1, with `path` the way: (x, y, heading, whether a whole move
    ends there) at every time unit after the start, a turn's or a step back's units spread evenly
    over its move)."""
    ox, oy, nx, ny = lattice
    free = np.zeros((ny, nx), dtype=np.bool_)
    step_ok = np.zeros((ny, nx, 2), dtype=np.bool_)
    stay, depart, arrive = (np.zeros((units, ny, nx), dtype=np.bool_) for _ in range(3))
    done = np.zeros(units, dtype=np.bool_)
    reach, nxt = (np.zeros((units + 1, 4, ny, nx), dtype=np.bool_) for _ in range(2))
    nwp = len(wps)
    came = np.zeros((nwp if path else 0, units + 1, 4, ny, nx), dtype=np.int8)
    goal = np.zeros(4, dtype=np.int64)
    period = int(_kinematic_search(occ, cell, float(radius_mm), discs, tracks, x0, y0, h0, LATTICE_MM, UNIT_PERIODS,
                                   np.ascontiguousarray(wps, dtype=np.float64), float(GOAL_TOL_MM), ox, oy, free,
                                   step_ok, stay, depart, arrive, done, reach, nxt, TURN_UNITS, REVERSE_UNITS,
                                   HEAD_DI, HEAD_DJ, came, goal, units + 1 if leg_slack is None else int(leg_slack)))
    if period < 0 or not path:
        return period, []

    k, (t, d, j, i) = nwp - 1, (int(v) for v in goal)
    moves = []  # (heading, j, i, move code) at each whole move's end, backwards
    while True:
        how = int(came[k, t, d, j, i])
        if how == _LEG_START:
            if k == 0:
                break  # the start
            k -= 1  # the previous leg ended here, then: its waypoint passed
            continue
        moves.append((d, j, i, how))
        if how == _K_STAYED:
            t -= 1
        elif how == _K_AHEAD:
            t, j, i = t - 1, j - HEAD_DJ[d], i - HEAD_DI[d]
        elif how == _K_LEFT:
            t, d = t - TURN_UNITS, (d + 3) % 4
        elif how == _K_RIGHT:
            t, d = t - TURN_UNITS, (d + 1) % 4
        else:  # _K_BACK
            t, j, i = t - REVERSE_UNITS, j + HEAD_DJ[d], i + HEAD_DI[d]
    way = []
    px, py = x0, y0
    for d, j, i, how in reversed(moves):
        x, y = ox + i * LATTICE_MM, oy + j * LATTICE_MM
        n = 1 if how in (_K_STAYED, _K_AHEAD) else (TURN_UNITS if how in (_K_LEFT, _K_RIGHT) else REVERSE_UNITS)
        way += [(px + (x - px) * u / n, py + (y - py) * u / n, d, u == n) for u in range(1, n + 1)]
        px, py = x, y
    return period, way
