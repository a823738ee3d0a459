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
  and waypoint advance) plus an optional clearance reward.
* `nav_eval_mem_kernel`: greedy rollouts of one table (plain or with the
  detour memory) over a list of scenario episodes (the `qnav bench nav` twin
  core); `obs_train_kernel` / `obs_mem_train_kernel`: the sector Q-learning
  loop drawing its episodes from a pool of scenarios.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ground_station.learn.jit import greedy, rand01, randint
from ground_station.learn.sector.kernels import (
    FWD_MM_PER_PERIOD,
    REVERSE,
    noisy_state,
)
from ground_station.learn.sector.memory import M_TURN, MEM_LEN, TURN_OF, memory_state
from ground_station.learn.sector.reward import (
    RW_ALIGN,
    RW_COLLISION,
    RW_GOAL,
    RW_PROGRESS,
    RW_REVERSE_COST,
    RW_STEP_COST,
)
from ground_station.learn.sector.twin import (
    _RAY_COS,
    _RAY_SIN,
    _SENS_COS,
    _SENS_SIN,
    ACTION_V_MM_S,
    ACTION_W_RAD_S,
    GOAL_TOL_MM,
    MAX_MOVE_MM,
    MOUNT_MM,
    N_SUBSTEPS,
    RADIUS_MM,
    RANGE_MAX,
    SUB_DT_S,
    _reading,
    bearing_mrad,
    disc_hits,
    encode_fast,
    ray_cast_dir,
    wrap_angle,
)
from sim_bridge import obstacles as sim_obstacles

step_movers = numba.njit(cache=True)(sim_obstacles.step_movers)
PERIOD_S = N_SUBSTEPS * SUB_DT_S
NEAR_MISS_MM = 50.0  # clearance to an unmapped obstacle below this (no contact) is a near miss
RW_CLEAR = 6  # extra reward slot: cost per period spent closer than clear_mm to an obstacle


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
def move_obs(occ, h, w, cell, x, y, th, action, discs, movers):
    """`twin.move` with discs and movers (frozen for the period) as obstacles."""
    v = ACTION_V_MM_S[action]
    om = ACTION_W_RAD_S[action]
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
        if v != 0.0 and (disc_hits(occ, h, w, cell, x, y, RADIUS_MM) or hits_discs(x, y, RADIUS_MM, discs, movers)):
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
def sense_obs(occ, h, w, cell, x, y, th, which, ranges, status, discs, movers) -> None:
    """`twin.sense` with the discs and movers in the rays' way."""
    ct = math.cos(th)
    st = math.sin(th)
    for i in range(ranges.shape[0]):
        if not which[i]:
            continue
        ox = x + MOUNT_MM * (ct * _SENS_COS[i] - st * _SENS_SIN[i])
        oy = y + MOUNT_MM * (st * _SENS_COS[i] + ct * _SENS_SIN[i])
        d = np.inf
        for k in range(_RAY_COS.shape[1]):
            cx = ct * _RAY_COS[i, k] - st * _RAY_SIN[i, k]
            cy = st * _RAY_COS[i, k] + ct * _RAY_SIN[i, k]
            t = ray_cast_dir(occ, h, w, cell, ox, oy, cx, cy, RANGE_MAX + 1.0)
            for j in range(discs.shape[0]):
                t = _ray_circle(ox, oy, cx, cy, discs[j, 0], discs[j, 1], discs[j, 2], t)
            for j in range(movers.shape[0]):
                t = _ray_circle(ox, oy, cx, cy, movers[j, 0], movers[j, 1], movers[j, 4], t)
            if t < d:
                d = t
        ranges[i], status[i] = _reading(d)


@numba.njit(cache=True)
def clearance_mm(occ, h, w, cell, x, y, discs, movers) -> float:
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
    for k in range(discs.shape[0]):
        d = math.sqrt((x - discs[k, 0]) ** 2 + (y - discs[k, 1]) ** 2) - discs[k, 2]
        if d < best:
            best = d
    for k in range(movers.shape[0]):
        d = math.sqrt((x - movers[k, 0]) ** 2 + (y - movers[k, 1]) ** 2) - movers[k, 4]
        if d < best:
            best = d
    return best - RADIUS_MM


@numba.njit(cache=True)
def obstacle_clearance_mm(x, y, discs, movers) -> float:
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
    return best - RADIUS_MM


@numba.njit(cache=True)
def obs_period_step(occ, h, w, c, x, y, th, phi, wps, rem, nwp, k, a, rw, which, ranges, status,
                    sectors, sensors, edges, discs, movers, clear_mm):
    """One control period with obstacles: robot moves (movers frozen), then
    the movers move (yielding to the robot's new pose), then the sensors
    read. Guide potential = straight distance to waypoint k + the waypoint
    path after it (wps[:nwp]; direct = the goal alone). Reward as
    `kernels.period_step`, minus rw[RW_CLEAR] while the clearance is below
    clear_mm. Returns (x, y, th, phi, reward, state, hit, success, driven, k)."""
    b0 = abs(bearing_mrad(x, y, th, wps[k, 0], wps[k, 1]))
    x, y, th, driven, hit = move_obs(occ, h, w, c, x, y, th, a, discs, movers)
    if hit:
        return x, y, th, phi, -rw[RW_COLLISION], -1, True, False, driven, k
    tol2 = GOAL_TOL_MM * GOAL_TOL_MM
    success = False
    while (x - wps[k, 0]) * (x - wps[k, 0]) + (y - wps[k, 1]) * (y - wps[k, 1]) <= tol2:
        if k == nwp - 1:
            success = True
            break
        k += 1
    phi2 = math.hypot(x - wps[k, 0], y - wps[k, 1]) + rem[k]
    r = rw[RW_PROGRESS] * (phi - phi2) / c - rw[RW_STEP_COST]
    if a == REVERSE:
        r -= rw[RW_REVERSE_COST]
    if rw[RW_ALIGN] != 0.0 and not success:
        r += rw[RW_ALIGN] * (b0 - abs(bearing_mrad(x, y, th, wps[k, 0], wps[k, 1]))) / 3141.5927
    if success:
        return x, y, th, phi2, r + rw[RW_GOAL], -1, False, True, driven, k
    step_movers(movers, occ, c, discs, x, y, RADIUS_MM, PERIOD_S)
    if rw[RW_CLEAR] != 0.0 and clear_mm > 0.0 and obstacle_clearance_mm(x, y, discs, movers) < clear_mm:
        r -= rw[RW_CLEAR]
    sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, movers)
    s2 = encode_fast(bearing_mrad(x, y, th, wps[k, 0], wps[k, 1]), ranges, status, sectors, sensors, edges)
    return x, y, th, phi2, r, s2, False, False, driven, k


# evaluation outcomes (as kernels: SUCCESS, COLLISION, LOOP, TIMEOUT)
SUCCESS, COLLISION, LOOP, TIMEOUT = 0, 1, 2, 3


@numba.njit(cache=True, inline="always")
def draw_pool_episode(rng, occ_all, dims, cells, ep_map, ep_start, ep_wp, ep_nwp, ep_rem, ep_discs, ep_nd,
                      ep_movers, ep_nm, start_pose_jitter_mm):
    """A training episode of the scenario pool, drawn uniformly, for every
    obstacle trainer: its map, discs, movers (copied: they move) and
    waypoints, the pool's start moved by up to start_pose_jitter_mm (kept
    where the moved start would touch something) and a random heading, and
    the guide potential there. Four uniform draws in this order, so each
    trainer replays the same episodes from the same seed. Returns
    (e, h, w, c, occ, discs, movers, wps, rem, nwp, x, y, th, phi), e the pool index."""
    e = randint(rng, ep_map.shape[0])
    m = ep_map[e]
    h = dims[m, 0]
    w = dims[m, 1]
    c = cells[m]
    occ = occ_all[m]
    discs = ep_discs[e, :ep_nd[e]]
    movers = ep_movers[e, :ep_nm[e]].copy()
    wps = ep_wp[e]
    rem = ep_rem[e]
    x = ep_start[e, 0] + (2.0 * rand01(rng) - 1.0) * start_pose_jitter_mm
    y = ep_start[e, 1] + (2.0 * rand01(rng) - 1.0) * start_pose_jitter_mm
    if disc_hits(occ, h, w, c, x, y, RADIUS_MM) or hits_discs(x, y, RADIUS_MM + MAX_MOVE_MM, discs, movers):
        x = ep_start[e, 0]
        y = ep_start[e, 1]
    th = (2.0 * rand01(rng) - 1.0) * math.pi
    phi = math.hypot(x - wps[0, 0], y - wps[0, 1]) + rem[0]
    return e, h, w, c, occ, discs, movers, wps, rem, ep_nwp[e], x, y, th, phi


@numba.njit(cache=True, inline="always")
def open_bench_episode(e, occ_all, dims, cells, ep_map, ep_start, ep_goal, ep_wp, ep_nwp, ep_rem, ep_discs,
                       ep_nd, ep_movers, ep_nm, guided, gwp, grem, budget_base, budget_factor):
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
    budget = int(budget_base + budget_factor * plan_len / FWD_MM_PER_PERIOD)
    phi = math.hypot(x - wps[0, 0], y - wps[0, 1]) + rem[0]
    return h, w, c, occ, discs, movers, wps, rem, nwp, x, y, th, budget, phi


@numba.njit(cache=True, inline="always")
def explore_or_greedy(q, rng, s: int, t: int, eps_start: float, eps_end: float, eps_decay_steps: int) -> int:
    """The obstacle trainers' epsilon-greedy choice at global step t (epsilon
    linear from eps_start to eps_end over eps_decay_steps, then held)."""
    frac = (t / eps_decay_steps) if eps_decay_steps > 0 else 1.0
    eps = eps_start + (eps_end - eps_start) * min(1.0, frac)
    if rand01(rng) < eps:
        return randint(rng, q.shape[1])
    return greedy(q, s)


@numba.njit(cache=True, inline="always")
def held_update(q, frozen, s0: int, a: int, s2: int, racc: float, g: float, terminal: bool, lr: float,
                lr_end: float, t: int, total_steps: int) -> None:
    """The semi-Markov Q update of action a held from state s0 (discounted
    return racc, discount g of the state reached s2; no bootstrap when
    terminal), the learning rate linear from lr to lr_end over total_steps;
    rows with frozen[s0] set keep their values (frozen of length 0: none)."""
    target = racc if terminal else racc + g * q[s2, greedy(q, s2)]
    fr = min(1.0, t / total_steps) if total_steps > 0 else 0.0
    if frozen.shape[0] == 0 or not frozen[s0]:
        q[s0, a] += (lr + (lr_end - lr) * fr) * (target - q[s0, a])


@numba.njit(cache=True, inline="always")
def stall_check(phi: float, best: float, since: int, stall_steps: int):
    """The bench's loop rule during training: (best, since, stalled) after a
    period whose guide potential is phi (stalled: no new minimum for
    stall_steps periods)."""
    if phi < best - 1.0:
        return phi, 0, False
    return best, since + 1, since + 1 >= stall_steps


@numba.njit(cache=True, inline="always")
def close_period(q, frozen, s, s0: int, a: int, s2: int, r: float, hit: bool, success: bool, phi: float,
                 t: int, i: int, hold: int, best: float, since: int, racc: float, ret: float, g: float,
                 gamma: float, stall_steps: int, stall_cost: float, max_episode_steps: int, n_steps: int,
                 hold_max: int, lr: float, lr_end: float, start_step: int, total_steps: int):
    """The end of a training period for the held-action trainers with memory (obs_mem_train_kernel,
    the sector-unmapped trainer): the stall rule (cost stall_cost, episode over), the discounted
    reward of the held action, its semi-Markov update when the hold ends (episode end, a new state
    or hold_max periods). Returns (s, t, i, hold, best, since, racc, ret, g, end)."""
    t += 1
    i += 1
    hold += 1
    stalled = False
    if stall_steps > 0 and not (hit or success):
        best, since, stalled = stall_check(phi, best, since, stall_steps)
        if stalled:
            r -= stall_cost
    racc += g * r
    ret += r
    g *= gamma
    terminal = hit or success or stalled
    end = terminal or t >= max_episode_steps or i >= n_steps
    if end or s2 != s0 or hold >= hold_max:
        held_update(q, frozen, s0, a, s2, racc, g, terminal, lr, lr_end, start_step + i, total_steps)
        hold = 0
    if not terminal:
        s = s2
    return s, t, i, hold, best, since, racc, ret, g, end


@numba.njit(cache=True)
def obs_train_kernel(q, rng, occ_all, dims, cells, ep_map, ep_start, ep_wp, ep_nwp, ep_rem,
                     ep_discs, ep_nd, ep_movers, ep_nm, sectors, sensors, edges, which,
                     lr, lr_end, gamma, eps_start, eps_end, eps_decay_steps, rw, clear_mm,
                     max_episode_steps, hold_max, noise_mm, start_pose_jitter_mm, start_step, total_steps,
                     n_steps, out_ret, out_succ):
    """Exact sequential Q-learning (as `kernels.train_kernel`: epsilon-greedy,
    linear lr decay, actions held while the state is unchanged up to
    hold_max periods, noisy range readings) on episodes drawn uniformly
    from the scenario pool, each started from the pool's start pose moved by
    up to start_pose_jitter_mm and a random heading. Runs n_steps periods in
    one call (whole episodes, so the last may be cut: it then bootstraps).
    Writes each finished episode's success to out_succ; returns the count."""
    ranges = np.zeros(which.shape[0], dtype=np.int64)
    status = np.zeros(which.shape[0], dtype=np.int64)
    noisy = np.zeros(which.shape[0], dtype=np.int64)
    nstatus = np.zeros(which.shape[0], dtype=np.int64)
    no_frozen = np.zeros(0, dtype=np.bool_)
    n_done = 0
    i = 0
    while i < n_steps:
        e, h, w, c, occ, discs, movers, wps, rem, nwp, x, y, th, phi = draw_pool_episode(
            rng, occ_all, dims, cells, ep_map, ep_start, ep_wp, ep_nwp, ep_rem, ep_discs, ep_nd, ep_movers, ep_nm,
            start_pose_jitter_mm)
        k = 0
        sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, movers)
        s = encode_fast(bearing_mrad(x, y, th, wps[0, 0], wps[0, 1]), ranges, status, sectors, sensors, edges)
        t = 0
        hold = 0
        a = 0
        s0 = s
        racc = 0.0
        g = 1.0
        success = False
        ret = 0.0
        while True:
            if hold == 0:
                a = explore_or_greedy(q, rng, s, start_step + i, eps_start, eps_end, eps_decay_steps)
                s0 = s
                racc = 0.0
                g = 1.0
            x, y, th, phi, r, s2, hit, success, _, k = obs_period_step(
                occ, h, w, c, x, y, th, phi, wps, rem, nwp, k, a, rw, which, ranges, status,
                sectors, sensors, edges, discs, movers, clear_mm)
            if noise_mm > 0.0 and not (hit or success):
                s2 = noisy_state(rng, noise_mm, x, y, th, wps[k, 0], wps[k, 1], ranges, status, noisy,
                                 nstatus, sectors, sensors, edges)
            t += 1
            i += 1
            hold += 1
            racc += g * r
            ret += r
            g *= gamma
            terminal = hit or success
            end = terminal or t >= max_episode_steps or i >= n_steps
            if end or s2 != s0 or hold >= hold_max:
                held_update(q, no_frozen, s0, a, s2, racc, g, terminal, lr, lr_end, start_step + i, total_steps)
                hold = 0
            if not terminal:
                s = s2
            if end:
                break
        out_ret[n_done] = ret
        out_succ[n_done] = success
        n_done += 1
    return n_done


# --- the detour memory (a `MemorySectorEncoder` with the planner's waypoints) ----------------

@numba.njit(cache=True)
def _mem_state(use_mem, mem, base_state, n_base, x, y, th, gx, gy, ranges, status, mp) -> int:
    if not use_mem:
        return base_state
    return memory_state(mem, base_state, n_base, x, y, th, gx, gy, ranges, status, mp)


@numba.njit(cache=True)
def nav_eval_mem_kernel(q, occ_all, dims, cells, ep_map, ep_start, ep_goal, ep_wp, ep_nwp, ep_rem,
                        ep_discs, ep_nd, ep_movers, ep_nm, sectors, sensors, edges, which, guided,
                        budget_base, budget_factor, stall_steps, mp, n_base,
                        out_outcome, out_path, out_steps, out_minclear, out_near):
    """Greedy rollouts of table q over scenario episodes e (map ep_map[e],
    start pose ep_start[e] = (x, y, th), goal point ep_goal[e], waypoints
    ep_wp[e, :ep_nwp[e]] with remaining lengths ep_rem[e], discs
    ep_discs[e, :ep_nd[e]], movers ep_movers[e, :ep_nm[e]] (copied: the
    scenario arrays stay as given)). guided = 0 steers on the goal alone.
    Outcomes: SUCCESS, COLLISION, LOOP (no new minimum of the guide
    potential for stall_steps periods), TIMEOUT (budget_base + budget_factor
    x planned path length in forward periods). Also: driven length, steps,
    minimum clearance, periods with clearance < NEAR_MISS_MM.

    For a `MemorySectorEncoder` table (mp =
    `memory_train.memory_params`, n_base = the base encoder's states): the
    Bug memory is reset at the start and whenever the current waypoint
    changes (as the robot's controller does per mission item), updated from
    all eight readings every period, and the previous action's turn is
    noted after each choice. mp of length 0: a plain sector table."""
    use_mem = mp.shape[0] > 0
    ranges = np.zeros(which.shape[0], dtype=np.int64)
    status = np.zeros(which.shape[0], dtype=np.int64)
    mem = np.zeros(MEM_LEN, dtype=np.int64)
    rw = np.zeros(7)
    gwp = np.zeros((1, 2))
    grem = np.zeros(1)
    for e in range(ep_map.shape[0]):
        h, w, c, occ, discs, movers, wps, rem, nwp, x, y, th, budget, phi = open_bench_episode(
            e, occ_all, dims, cells, ep_map, ep_start, ep_goal, ep_wp, ep_nwp, ep_rem, ep_discs, ep_nd, ep_movers,
            ep_nm, guided, gwp, grem, budget_base, budget_factor)
        k = 0
        best = phi
        since = 0
        path = 0.0
        outcome = TIMEOUT
        minclear = obstacle_clearance_mm(x, y, discs, movers)
        near = 0
        t = 0
        mem[:] = 0
        sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, movers)
        s = encode_fast(bearing_mrad(x, y, th, wps[0, 0], wps[0, 1]), ranges, status, sectors, sensors, edges)
        s = _mem_state(use_mem, mem, s, n_base, x, y, th, wps[0, 0], wps[0, 1], ranges, status, mp)
        while t < budget:
            a = greedy(q, s)
            mem[M_TURN] = TURN_OF[a]
            k0 = k
            x, y, th, phi, _, s, hit, success, driven, k = obs_period_step(
                occ, h, w, c, x, y, th, phi, wps, rem, nwp, k, a, rw, which, ranges, status,
                sectors, sensors, edges, discs, movers, 0.0)
            path += driven
            t += 1
            if hit:
                outcome = COLLISION
                minclear = 0.0
                break
            if k != k0:
                mem[:] = 0
            cl = obstacle_clearance_mm(x, y, discs, movers)
            if cl < minclear:
                minclear = cl
            if cl < NEAR_MISS_MM:
                near += 1
            if success:
                outcome = SUCCESS
                break
            s = _mem_state(use_mem, mem, s, n_base, x, y, th, wps[k, 0], wps[k, 1], ranges, status, mp)
            best, since, stalled = stall_check(phi, best, since, stall_steps)
            if stalled:
                outcome = LOOP
                break
        out_outcome[e] = outcome
        out_path[e] = path
        out_steps[e] = t
        out_minclear[e] = minclear
        out_near[e] = near


@numba.njit(cache=True)
def obs_mem_train_kernel(q, rng, occ_all, dims, cells, ep_map, ep_start, ep_wp, ep_nwp, ep_rem,
                         ep_discs, ep_nd, ep_movers, ep_nm, sectors, sensors, edges, which, mp, n_base, frozen,
                         stall_steps, stall_cost,
                         lr, lr_end, gamma, eps_start, eps_end, eps_decay_steps, rw, clear_mm,
                         max_episode_steps, hold_max, noise_mm, start_pose_jitter_mm, start_step, total_steps,
                         n_steps, out_ret, out_succ):
    """`obs_train_kernel` with the detour memory of `nav_eval_mem_kernel`
    in the state (reset per waypoint, updated from the same noisy readings
    the state is encoded from, the previous turn noted per choice); the
    reward is the waypoint-progress reward of `obs_period_step` in every
    mode. Rows s with frozen[s] set keep their values (e.g. go rows copied
    from a trained sector table while the wall rows learn); frozen of
    length 0 freezes nothing. stall_steps > 0: an episode whose guide
    potential has found no new minimum for stall_steps periods (the bench's
    loop rule) ends there as a failure, with reward -stall_cost (what the
    bench counts as a loop is then as bad for the learner as it is for the
    figure). mp of length 0, frozen empty, stall_steps 0: exactly
    `obs_train_kernel`'s updates."""
    use_mem = mp.shape[0] > 0
    ranges = np.zeros(which.shape[0], dtype=np.int64)
    status = np.zeros(which.shape[0], dtype=np.int64)
    noisy = np.zeros(which.shape[0], dtype=np.int64)
    nstatus = np.zeros(which.shape[0], dtype=np.int64)
    mem = np.zeros(MEM_LEN, dtype=np.int64)
    n_done = 0
    i = 0
    while i < n_steps:
        e, h, w, c, occ, discs, movers, wps, rem, nwp, x, y, th, phi = draw_pool_episode(
            rng, occ_all, dims, cells, ep_map, ep_start, ep_wp, ep_nwp, ep_rem, ep_discs, ep_nd, ep_movers, ep_nm,
            start_pose_jitter_mm)
        k = 0
        best = phi
        since = 0
        mem[:] = 0
        sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, movers)
        s = encode_fast(bearing_mrad(x, y, th, wps[0, 0], wps[0, 1]), ranges, status, sectors, sensors, edges)
        s = _mem_state(use_mem, mem, s, n_base, x, y, th, wps[0, 0], wps[0, 1], ranges, status, mp)
        t = 0
        hold = 0
        a = 0
        s0 = s
        racc = 0.0
        g = 1.0
        success = False
        ret = 0.0
        while True:
            if hold == 0:
                a = explore_or_greedy(q, rng, s, start_step + i, eps_start, eps_end, eps_decay_steps)
                s0 = s
                racc = 0.0
                g = 1.0
            mem[M_TURN] = TURN_OF[a]
            k0 = k
            x, y, th, phi, r, s2, hit, success, _, k = obs_period_step(
                occ, h, w, c, x, y, th, phi, wps, rem, nwp, k, a, rw, which, ranges, status,
                sectors, sensors, edges, discs, movers, clear_mm)
            if not (hit or success):
                if k != k0:
                    mem[:] = 0
                    mem[M_TURN] = TURN_OF[a]
                if noise_mm > 0.0:
                    noisy[:] = ranges
                    nstatus[:] = status
                    s2 = noisy_state(rng, noise_mm, x, y, th, wps[k, 0], wps[k, 1], ranges, status, noisy,
                                     nstatus, sectors, sensors, edges)
                    s2 = _mem_state(use_mem, mem, s2, n_base, x, y, th, wps[k, 0], wps[k, 1], noisy, nstatus, mp)
                else:
                    s2 = _mem_state(use_mem, mem, s2, n_base, x, y, th, wps[k, 0], wps[k, 1], ranges, status, mp)
            s, t, i, hold, best, since, racc, ret, g, end = close_period(
                q, frozen, s, s0, a, s2, r, hit, success, phi, t, i, hold, best, since, racc, ret, g, gamma,
                stall_steps, stall_cost, max_episode_steps, n_steps, hold_max, lr, lr_end, start_step,
                total_steps)
            if end:
                break
        out_ret[n_done] = ret
        out_succ[n_done] = success
        n_done += 1
    return n_done
