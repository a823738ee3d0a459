"""The kinematic twin with unmapped obstacles: discs and movers (numba).

Additive to `ground_station.learn.sector.twin` (which knows only the grid):
the same motion, sensing and reward with a scenario's static discs
(float64 (K, 3): x, y, r mm) and movers ((M, 5): x, y, vx, vy, r) added to
what the robot can hit and what its range rays see. Movers move once per
control period after the robot, by `sim_bridge.obstacles.step_movers`
compiled here from the sim's own source (one definition for both).

* `move_obs` / `sense_obs` / `clearance_mm`: the twin's `move` / `sense` with
  the discs, and the robot's clearance (surface to the nearest wall, cell,
  disc or mover) for near-miss counting.
* `obs_period_step`: `kernels.period_step` with obstacles (same reward terms
  and waypoint advance).
* `nav_eval_kernel`: greedy rollouts of one sector table over a list of
  scenario episodes (the `qnav bench nav` twin core).
"""

from __future__ import annotations

import math

import numpy as np

from ground_station.jitcache import numba
from ground_station.learn.jit import greedy
from ground_station.learn.sector.kernels import pass_waypoints, progress_reward
from ground_station.learn.sector.reward import (
    RW_ALIGN,
    RW_COLLISION,
    RW_GOAL,
)
from ground_station.learn.sector.twin import (
    G_FWD,
    G_RADIUS,
    N_SUBSTEPS,
    SUB_DT_S,
    TW_GEO,
    TW_RCOS,
    TW_RMAX,
    TW_V,
    TW_W,
    _reading,
    bearing_mrad,
    disc_hits,
    encode_fast,
    fan_distance,
    fan_ray,
    wrap_angle,
)
from sim_bridge import obstacles as sim_obstacles

step_movers = numba.njit(cache=True)(sim_obstacles.step_movers)
PERIOD_S = N_SUBSTEPS * SUB_DT_S
NEAR_MISS_MM = 50.0  # clearance to an unmapped obstacle below this (no contact) is a near miss


@numba.njit(cache=True)
def hits_discs(x: float, y: float, r: float, discs, movers) -> bool:
    for k in range(discs.shape[0]):
        d = r + discs[k, 2]
        if (x - discs[k, 0]) ** 2 + (y - discs[k, 1]) ** 2 < d * d:
            return True
    for k in range(movers.shape[0]):
        d = r + movers[k, 4]
        if (x - movers[k, 0]) ** 2 + (y - movers[k, 1]) ** 2 < d * d:
            return True
    return False


@numba.njit(cache=True)
def move_obs(occ, h, w, cell, x, y, th, action, discs, movers, tw):
    """`twin.move` with discs and movers (frozen for the period) as obstacles (the robot `tw`)."""
    v = tw[TW_V][action]
    om = tw[TW_W][action]
    radius = tw[TW_GEO][G_RADIUS]
    driven = 0.0
    for _ in range(N_SUBSTEPS):
        if om == 0.0:
            x += v * SUB_DT_S * math.cos(th)
            y += v * SUB_DT_S * math.sin(th)
            th2 = th
        else:
            th2 = th + om * SUB_DT_S
            x += v / om * (math.sin(th2) - math.sin(th))
            y -= v / om * (math.cos(th2) - math.cos(th))
        th = th2
        driven += abs(v) * SUB_DT_S
        if v != 0.0 and (disc_hits(occ, h, w, cell, x, y, radius) or hits_discs(x, y, radius, discs, movers)):
            return x, y, wrap_angle(th), driven, True
    return x, y, wrap_angle(th), driven, False


@numba.njit(cache=True, inline="always")
def _ray_circle(ox, oy, cx, cy, px, py, rad, best):
    fx = px - ox
    fy = py - oy
    c2 = fx * fx + fy * fy - rad * rad
    if c2 <= 0.0:
        return 0.0
    b = fx * cx + fy * cy
    if b <= 0.0:
        return best
    disc = b * b - c2
    if disc < 0.0:
        return best
    t = b - math.sqrt(disc)
    return t if t < best else best


@numba.njit(cache=True)
def sense_obs(occ, h, w, cell, x, y, th, which, ranges, status, discs, movers, tw) -> None:
    """`twin.sense` with the discs and movers in the rays' way: the fan's
    nearest cell hit, then each ray's nearest disc or mover if nearer (the
    minimum over rays and obstacles, the same number in either order)."""
    ct = math.cos(th)
    st = math.sin(th)
    for i in range(ranges.shape[0]):
        if not which[i]:
            continue
        d = fan_distance(occ, h, w, cell, x, y, ct, st, i, tw)
        for k in range(tw[TW_RCOS].shape[1]):
            ox, oy, cx, cy = fan_ray(x, y, ct, st, i, k, tw)
            for j in range(discs.shape[0]):
                d = _ray_circle(ox, oy, cx, cy, discs[j, 0], discs[j, 1], discs[j, 2], d)
            for j in range(movers.shape[0]):
                d = _ray_circle(ox, oy, cx, cy, movers[j, 0], movers[j, 1], movers[j, 4], d)
        ranges[i], status[i] = _reading(d, tw[TW_RMAX][i])


@numba.njit(cache=True)
def clearance_mm(occ, h, w, cell, x, y, discs, movers, radius) -> float:
    """Distance from the robot's rim to the nearest obstacle cell, border,
    disc or mover (<= 0: contact); cells farther than 2 cells are not looked at."""
    best = min(x, y, w * cell - x, h * cell - y)
    col = int(math.floor(x / cell))
    row = h - 1 - int(math.floor(y / cell))
    top = h * cell
    for r in range(max(0, row - 2), min(h, row + 3)):
        ylo = top - (r + 1) * cell
        for c in range(max(0, col - 2), min(w, col + 3)):
            if occ[r, c]:
                xlo = c * cell
                px = min(max(x, xlo), xlo + cell)
                py = min(max(y, ylo), ylo + cell)
                d = math.sqrt((x - px) ** 2 + (y - py) ** 2)
                if d < best:
                    best = d
    return min(best - radius, obstacle_clearance_mm(x, y, discs, movers, radius))


@numba.njit(cache=True)
def obstacle_clearance_mm(x, y, discs, movers, radius) -> float:
    """Distance from the robot's rim to the nearest unmapped obstacle (disc or
    mover); inf without any. The near-miss figure counts these only: the
    map's own walls are the planner's business (a one-cell corridor leaves
    100 mm a side)."""
    best = np.inf
    for k in range(discs.shape[0]):
        d = math.sqrt((x - discs[k, 0]) ** 2 + (y - discs[k, 1]) ** 2) - discs[k, 2]
        if d < best:
            best = d
    for k in range(movers.shape[0]):
        d = math.sqrt((x - movers[k, 0]) ** 2 + (y - movers[k, 1]) ** 2) - movers[k, 4]
        if d < best:
            best = d
    return best - radius


@numba.njit(cache=True)
def obs_period_step(occ, h, w, c, x, y, th, phi, wps, rem, nwp, k, a, rw, which, ranges, status,
                    sectors, sensors, edges, discs, movers, tw):
    """One control period with obstacles: robot moves (movers frozen), then
    the movers move (yielding to the robot's new pose), then the sensors
    read. Guide potential = straight distance to waypoint k + the waypoint
    path after it (wps[:nwp]; direct = the goal alone). Reward as
    `kernels.period_step` (rw indexed by the `RW_*` slots; the bench passes
    zeros). Returns (x, y, th, phi, reward, state, hit, success, driven, k)."""
    b0 = abs(bearing_mrad(x, y, th, wps[k, 0], wps[k, 1]))
    x, y, th, driven, hit = move_obs(occ, h, w, c, x, y, th, a, discs, movers, tw)
    if hit:
        return x, y, th, phi, -rw[RW_COLLISION], -1, True, False, driven, k
    k, success = pass_waypoints(x, y, wps, nwp, k)
    phi2 = math.hypot(x - wps[k, 0], y - wps[k, 1]) + rem[k]
    r = progress_reward(rw, phi, phi2, c, a)
    if rw[RW_ALIGN] != 0.0 and not success:
        r += rw[RW_ALIGN] * (b0 - abs(bearing_mrad(x, y, th, wps[k, 0], wps[k, 1]))) / 3141.5927
    if success:
        return x, y, th, phi2, r + rw[RW_GOAL], -1, False, True, driven, k
    step_movers(movers, occ, c, discs, x, y, tw[TW_GEO][G_RADIUS], PERIOD_S)
    sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, movers, tw)
    s2 = encode_fast(bearing_mrad(x, y, th, wps[k, 0], wps[k, 1]), ranges, status, sectors, sensors, edges)
    return x, y, th, phi2, r, s2, False, False, driven, k


# evaluation outcomes (as kernels: SUCCESS, COLLISION, LOOP, TIMEOUT)
SUCCESS, COLLISION, LOOP, TIMEOUT = 0, 1, 2, 3
NO_ROUTE = 4  # the robot reported that no route to the goal exists (blocked-passage scenarios)


@numba.njit(cache=True, inline="always")
def open_bench_episode(e, occ_all, dims, cells, ep_map, ep_start, ep_goal, ep_wp, ep_nwp, ep_rem, ep_discs,
                       ep_nd, ep_movers, ep_nm, guided, gwp, grem, budget_base, budget_factor, tw):
    """Scenario episode e as every bench kernel rolls it out: its map, discs,
    movers (copied: they move), the waypoints (guided) or the goal alone (in
    gwp, grem), the start pose, the period budget (budget_base +
    budget_factor x planned length in forward periods) and the guide
    potential. Returns (h, w, c, occ, discs, movers, wps, rem, nwp, x, y, th, budget, phi)."""
    m = ep_map[e]
    h = dims[m, 0]
    w = dims[m, 1]
    c = cells[m]
    occ = occ_all[m]
    discs = ep_discs[e, :ep_nd[e]]
    movers = ep_movers[e, :ep_nm[e]].copy()
    if guided:
        wps = ep_wp[e]
        rem = ep_rem[e]
        nwp = ep_nwp[e]
    else:
        gwp[0, 0] = ep_goal[e, 0]
        gwp[0, 1] = ep_goal[e, 1]
        wps = gwp
        rem = grem
        nwp = 1
    x = ep_start[e, 0]
    y = ep_start[e, 1]
    th = ep_start[e, 2]
    plan_len = ep_rem[e, 0] + math.hypot(x - ep_wp[e, 0, 0], y - ep_wp[e, 0, 1])
    budget = int(budget_base + budget_factor * plan_len / tw[TW_GEO][G_FWD])
    phi = math.hypot(x - wps[0, 0], y - wps[0, 1]) + rem[0]
    return h, w, c, occ, discs, movers, wps, rem, nwp, x, y, th, budget, phi


@numba.njit(cache=True, inline="always")
def stall_check(phi: float, best: float, since: int, stall_steps: int):
    """The bench's loop rule: (best, since, stalled) after a period whose
    guide potential is phi (stalled: no new minimum for stall_steps periods)."""
    if phi < best - 1.0:
        return phi, 0, False
    return best, since + 1, since + 1 >= stall_steps


@numba.njit(cache=True)
def period_end(x, y, discs, movers, success, phi, best, since, stall_steps, minclear, near, radius):
    """After a period without a collision: the clearance figures (the minimum so far, periods
    nearer than NEAR_MISS_MM) and how the episode ends: SUCCESS, LOOP (`stall_check`), or -1 to
    go on. Returns (end, best, since, minclear, near)."""
    cl = obstacle_clearance_mm(x, y, discs, movers, radius)
    if cl < minclear:
        minclear = cl
    if cl < NEAR_MISS_MM:
        near += 1
    if success:
        return SUCCESS, best, since, minclear, near
    best, since, stalled = stall_check(phi, best, since, stall_steps)
    return (LOOP if stalled else -1), best, since, minclear, near


@numba.njit(cache=True)
def nav_eval_kernel(q, occ_all, dims, cells, ep_map, ep_start, ep_goal, ep_wp, ep_nwp, ep_rem,
                    ep_discs, ep_nd, ep_movers, ep_nm, sectors, sensors, edges, which, guided,
                    budget_base, budget_factor, stall_steps,
                    out_outcome, out_path, out_steps, out_minclear, out_near, tw):
    """Greedy rollouts of table q over scenario episodes e (map ep_map[e],
    start pose ep_start[e] = (x, y, th), goal point ep_goal[e], waypoints
    ep_wp[e, :ep_nwp[e]] with remaining lengths ep_rem[e], discs
    ep_discs[e, :ep_nd[e]], movers ep_movers[e, :ep_nm[e]] (copied: the
    scenario arrays stay as given)). guided = 0 steers on the goal alone.
    Outcomes: SUCCESS, COLLISION, LOOP (no new minimum of the guide
    potential for stall_steps periods), TIMEOUT (budget_base + budget_factor
    x planned path length in forward periods). Also: driven length, steps,
    minimum clearance, periods with clearance < NEAR_MISS_MM."""
    ranges = np.zeros(which.shape[0], dtype=np.int64)
    status = np.zeros(which.shape[0], dtype=np.int64)
    rw = np.zeros(6)
    gwp = np.zeros((1, 2))
    grem = np.zeros(1)
    for e in range(ep_map.shape[0]):
        h, w, c, occ, discs, movers, wps, rem, nwp, x, y, th, budget, phi = open_bench_episode(
            e, occ_all, dims, cells, ep_map, ep_start, ep_goal, ep_wp, ep_nwp, ep_rem, ep_discs, ep_nd, ep_movers,
            ep_nm, guided, gwp, grem, budget_base, budget_factor, tw)
        radius = tw[TW_GEO][G_RADIUS]
        k = 0
        best = phi
        since = 0
        path = 0.0
        outcome = TIMEOUT
        minclear = obstacle_clearance_mm(x, y, discs, movers, radius)
        near = 0
        t = 0
        sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, movers, tw)
        s = encode_fast(bearing_mrad(x, y, th, wps[0, 0], wps[0, 1]), ranges, status, sectors, sensors, edges)
        while t < budget:
            a = greedy(q, s)
            x, y, th, phi, _, s, hit, success, driven, k = obs_period_step(
                occ, h, w, c, x, y, th, phi, wps, rem, nwp, k, a, rw, which, ranges, status,
                sectors, sensors, edges, discs, movers, tw)
            path += driven
            t += 1
            if hit:
                outcome = COLLISION
                minclear = 0.0
                break
            end, best, since, minclear, near = period_end(x, y, discs, movers, success, phi, best, since,
                                                          stall_steps, minclear, near, radius)
            if end >= 0:
                outcome = end
                break
        out_outcome[e] = outcome
        out_path[e] = path
        out_steps[e] = t
        out_minclear[e] = minclear
        out_near[e] = near
