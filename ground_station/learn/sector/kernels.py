"""Jitted kernels of the sector encoding: the exact sequential Q-learning loop and
greedy evaluation rollouts, both on the kinematic twin (`sector.twin`).

Maps are packed for numba: `occ` uint8 (M, Hmax, Wmax) padded with
obstacles, `dims` int64 (M, 2) = (H, W), `cell` float64 (M,) mm, free cells
`free` int64 (M, Fmax, 2) = (col, row) with counts `nfree`, and per map the
octile distance field (cells) to every free cell `dist` float32
(M, Fmax, Hmax, Wmax). Random numbers come from a xorshift64* generator whose
state lives in a caller-owned array, so a run split into chunks draws exactly
the same numbers as one call (same seed -> same table).

Guidance: with `guided` set, every episode follows the planner's waypoints
(last = the goal), the state's bearing is to the current waypoint and the
waypoint advances inside GOAL_TOLERANCE_MM, exactly as the robot runs a
mission; without it the bearing is to the goal (pure reactive).

Reward of one control period (weights `rw` = `SectorReward.array()`, slots
`RW_*` of `ground_station.learn.sector.reward`):
  progress x (progress in cells along the guide potential) - step_cost
  - reverse_cost extra if the action is `reverse`
  + align x (turn of the target's bearing toward straight ahead, per pi rad);
  on reaching the goal + goal; on a collision -collision (and nothing else).
The guide potential is `guide_potential`'s.
"""

from __future__ import annotations

import math

import numpy as np

from firmware_py import robot_spec
from ground_station.jitcache import numba
from ground_station.learn.jit import (
    double_q_update,
    dyna_q_update,
    epsilon_at,
    expected_value,
    greedy,
    greedy_sum,
    q_lambda_update,
    rand01,
    randint,
)
from ground_station.learn.sector.reward import (
    RW_ALIGN,
    RW_COLLISION,
    RW_GOAL,
    RW_PROGRESS,
    RW_REVERSE_COST,
    RW_STEP_COST,
)
from ground_station.learn.sector.twin import (
    DEFAULT_TW,
    G_FWD,
    G_RADIUS,
    GOAL_TOL_MM,
    N_ACTIONS,
    TW_GEO,
    TW_RMAX,
    bearing_mrad,
    bearing_sector_fast,
    cell_centre,
    encode_fast,
    move,
    potential,
    sense,
    sense_bordered,
)
from ground_station.maps.planner import plan_into, remaining_lengths

# fastest forward travel in one control period (the step budget's unit), of the built-in robot
# (a profile's: tw[TW_GEO][G_FWD])
FWD_MM_PER_PERIOD = float(DEFAULT_TW[TW_GEO][G_FWD])

REVERSE = 3  # index of `reverse` in robot_spec.ACTION_NAMES (asserted in tests)
RANGE_VALID_, RANGE_TOO_CLOSE_, RANGE_TOO_FAR_ = robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_CLOSE, robot_spec.RANGE_TOO_FAR
RANGE_MIN_ = robot_spec.RANGE_MIN_MM

# episode-state slots (float64 array carried between chunks)
(E_ACTIVE, E_MAP, E_X, E_Y, E_TH, E_GOAL, E_GX, E_GY, E_T, E_RET, E_S, E_PHI,
 E_K, E_A, E_S0, E_R, E_G, E_NWP, E_WP, E_NEXT) = range(20)
EP_LEN = 20


@numba.njit(cache=True)
def gauss(rng) -> float:
    """Standard normal draw (Box-Muller) from the xorshift state."""
    u = rand01(rng)
    v = rand01(rng)
    return math.sqrt(-2.0 * math.log(1.0 - u)) * math.cos(2.0 * math.pi * v)


# |Box-Muller draw| <= sqrt(-2 ln 2^-53) = 8.5717 (rand01 <= 1 - 2^-53, so 1 - u >= 2^-53)
GAUSS_MAX = 8.6


@numba.njit(cache=True, inline="always")
def _noisy_bin(r, edges, rmax) -> int:
    """`encode_fast`'s range bin of a noisy reading r (mm) before the sensor limits apply."""
    if r < RANGE_MIN_:
        return 0
    if r > rmax:
        return edges.shape[0]
    b = 0
    for e in range(edges.shape[0]):
        if r >= edges[e]:
            b += 1
    return b


@numba.njit(cache=True, inline="always")
def noisy_encode_fast(rng, noise_mm, bearing, ranges, status, nstatus, sectors, sensors, edges, tw) -> int:
    """The state index of the readings with Gaussian noise (std noise_mm, whole mm) added to the
    valid ones, re-classified past the sensor limits, as the sim's noisy sensors report: the index
    of the reference `noisy_state` (tests/support/sector_noise.py) with the same draws, the
    Gaussian computed only where it can change the index: the bin is monotone in the reading and a
    draw moves it by at most `bound` mm, so when both ends fall into one bin the two uniforms are
    drawn and dropped. No readings out."""
    bound = int(math.ceil(noise_mm * GAUSS_MAX)) + 1
    state = 0
    mult = 1
    nb = edges.shape[0] + 1
    for j in range(sensors.shape[0]):
        i = sensors[j]
        st = status[i]
        if st == RANGE_VALID_:
            r0 = ranges[i]
            rmax = tw[TW_RMAX][i]
            lo = _noisy_bin(r0 - bound, edges, rmax)
            if lo == _noisy_bin(r0 + bound, edges, rmax):
                rand01(rng)
                rand01(rng)
                b = lo
            else:
                b = _noisy_bin(r0 + int(math.floor(noise_mm * gauss(rng) + 0.5)), edges, rmax)
        elif st == RANGE_TOO_CLOSE_:
            b = 0
        else:
            b = nb - 1
        state += b * mult
        mult *= nb
    return bearing_sector_fast(bearing, sectors) * mult + state


@numba.njit(cache=True, inline="always")
def guide_potential(dist, occ, h, w, c, x, y, wps, rem, k, guided) -> float:
    """Remaining-path estimate (mm) of the reward and the loop detector: guided, the distance to
    waypoint k plus the path after it; direct, the goal's `potential`."""
    if guided:
        return math.hypot(x - wps[k, 0], y - wps[k, 1]) + rem[k]
    return potential(dist, occ, h, w, c, x, y)


@numba.njit(cache=True)
def start_guidance(occ, h, w, c, dist, x, y, gx, gy, guided, clear_r, max_seg, path, wps, rem) -> int:
    """Fill wps/rem from (x, y) to the goal: the planner's waypoints (`plan_into`) when guided,
    else the goal alone. Returns the waypoint count."""
    n = 0
    if guided:
        n = plan_into(occ, h, w, c, dist, x, y, clear_r, max_seg, path, wps)
    if n == 0:
        wps[0, 0] = gx
        wps[0, 1] = gy
        n = 1
    remaining_lengths(wps, n, rem)
    return n


@numba.njit(cache=True)
def _new_episode(ep, rng, occ, dims, cell, free, nfree, dist, sectors, sensors, edges, which,
                 ranges, status, guided, clear_r, max_seg, path, wps, rem, tw):
    m = randint(rng, occ.shape[0])
    h = dims[m, 0]
    w = dims[m, 1]
    c = cell[m]
    nf = nfree[m]
    g = randint(rng, nf)
    gcol = free[m, g, 0]
    grow = free[m, g, 1]
    d = dist[m, g]
    while True:  # a start cell connected to the goal, not the goal itself
        k = randint(rng, nf)
        scol = free[m, k, 0]
        srow = free[m, k, 1]
        if k != g and d[srow, scol] < np.inf:
            break
    half = 0.5 * c - tw[TW_GEO][G_RADIUS] - 1.0  # stays inside the start cell: no contact
    cx, cy = cell_centre(scol, srow, h, c)
    x = cx + (2.0 * rand01(rng) - 1.0) * half
    y = cy + (2.0 * rand01(rng) - 1.0) * half
    th = (2.0 * rand01(rng) - 1.0) * math.pi
    gx, gy = cell_centre(gcol, grow, h, c)
    og = occ[m]
    nwp = start_guidance(og, h, w, c, d, x, y, gx, gy, guided, clear_r, max_seg, path, wps, rem)
    sense(og, h, w, c, x, y, th, which, ranges, status, tw)
    ep[E_ACTIVE] = 1.0
    ep[E_MAP] = m
    ep[E_X] = x
    ep[E_Y] = y
    ep[E_TH] = th
    ep[E_GOAL] = g
    ep[E_GX] = gx
    ep[E_GY] = gy
    ep[E_T] = 0.0
    ep[E_RET] = 0.0
    ep[E_K] = 0.0
    ep[E_NWP] = nwp
    ep[E_WP] = 0.0
    ep[E_S] = encode_fast(bearing_mrad(x, y, th, wps[0, 0], wps[0, 1]), ranges, status, sectors, sensors, edges)
    ep[E_PHI] = guide_potential(d, og, h, w, c, x, y, wps, rem, 0, guided)


@numba.njit(cache=True, inline="always")
def pass_waypoints(x, y, wps, nwp, k):
    """Advance past every waypoint of wps[:nwp] from k that (x, y) is within GOAL_TOLERANCE_MM of,
    as the controller advances a mission item: (k, reached the last one)."""
    tol2 = GOAL_TOL_MM * GOAL_TOL_MM
    while (x - wps[k, 0]) * (x - wps[k, 0]) + (y - wps[k, 1]) * (y - wps[k, 1]) <= tol2:
        if k == nwp - 1:
            return k, True
        k += 1
    return k, False


@numba.njit(cache=True, inline="always")
def progress_reward(rw, phi, phi2, c, a) -> float:
    """One period's progress along the guide potential (phi -> phi2, in cells) less the step cost,
    and the reverse cost when action `a` reversed."""
    r = rw[RW_PROGRESS] * (phi - phi2) / c - rw[RW_STEP_COST]
    if a == REVERSE:
        r -= rw[RW_REVERSE_COST]
    return r


@numba.njit(cache=True)
def period_step(occ, h, w, c, dist, x, y, th, phi, wps, rem, nwp, k, a, rw, which, ranges, status,
                sectors, sensors, edges, guided, tw):
    """One control period from pose (x, y, th) with potential phi, heading for waypoint k of
    wps[:nwp]: the one definition of reward and waypoint advance (trainer, evaluation, Gymnasium
    env). Returns (x, y, th, phi, reward, state, hit, success, driven_mm, k); after a hit or
    success the state is -1 and ranges/status are not refreshed."""
    b0 = abs(bearing_mrad(x, y, th, wps[k, 0], wps[k, 1]))
    x, y, th, driven, hit = move(occ, h, w, c, x, y, th, a, tw)
    if hit:
        return x, y, th, phi, -rw[RW_COLLISION], -1, True, False, driven, k
    k, success = pass_waypoints(x, y, wps, nwp, k)
    phi2 = guide_potential(dist, occ, h, w, c, x, y, wps, rem, k, guided)
    r = progress_reward(rw, phi, phi2, c, a)
    if rw[RW_ALIGN] != 0.0 and not success:  # heading shaping: turning toward the target pays
        r += rw[RW_ALIGN] * (b0 - abs(bearing_mrad(x, y, th, wps[k, 0], wps[k, 1]))) / 3141.5927
    if success:
        return x, y, th, phi2, r + rw[RW_GOAL], -1, False, True, driven, k
    sense(occ, h, w, c, x, y, th, which, ranges, status, tw)
    s2 = encode_fast(bearing_mrad(x, y, th, wps[k, 0], wps[k, 1]), ranges, status, sectors, sensors, edges)
    return x, y, th, phi2, r, s2, False, False, driven, k


@numba.njit(cache=True, inline="always")
def train_period(occ, occb, h, w, c, dist, x, y, th, phi, b0, wps, rem, nwp, k, a, rw, which, ranges, status,
                 sectors, sensors, edges, guided, rng, noise_mm, noisy, nstatus, tw):
    """`period_step` for the trainer's hot loop, bit for bit (a test compares trained tables):
    b0 = |bearing| to waypoint k is carried from the previous period, the end bearing computed
    once, the sensors cast on the `bordered` grid occb, and with noise_mm > 0 the state comes
    from the noisy readings (the draws of `period_step` then tests/support's `noisy_state`).
    Returns (x, y, th, phi, reward, state, hit, success, k, |bearing|)."""
    x, y, th, driven, hit = move(occ, h, w, c, x, y, th, a, tw)
    if hit:
        return x, y, th, phi, -rw[RW_COLLISION], -1, True, False, k, b0
    k, success = pass_waypoints(x, y, wps, nwp, k)
    phi2 = guide_potential(dist, occ, h, w, c, x, y, wps, rem, k, guided)
    r = progress_reward(rw, phi, phi2, c, a)
    if success:
        return x, y, th, phi2, r + rw[RW_GOAL], -1, False, True, k, b0
    bm = bearing_mrad(x, y, th, wps[k, 0], wps[k, 1])
    b1 = float(abs(bm))
    if rw[RW_ALIGN] != 0.0:  # heading shaping: turning toward the target pays
        r += rw[RW_ALIGN] * (b0 - b1) / 3141.5927
    sense_bordered(occb, h, w, c, x, y, th, which, ranges, status, tw)
    if noise_mm > 0.0:
        s2 = noisy_encode_fast(rng, noise_mm, bm, ranges, status, nstatus, sectors, sensors, edges, tw)
    else:
        s2 = encode_fast(bm, ranges, status, sectors, sensors, edges)
    return x, y, th, phi2, r, s2, False, False, k, b1


# tabular learners of the sector trainer (`ground_station.learn.cell.learners`' switch, LEARNERS order)
L_Q, L_SARSA, L_EXPECTED_SARSA, L_DOUBLE_Q, L_DYNA_Q, L_Q_LAMBDA = range(6)


@numba.njit(cache=True, inline="always")
def _episode_views(ep, occ, occb, dist, dims, cell):
    """The open episode's (grid, bordered grid, goal distances, H, W, cell), taken once per
    episode: a view made in the loop costs two atomic reference-count updates per step."""
    m = int(ep[E_MAP])
    return occ[m], occb[m], dist[m, int(ep[E_GOAL])], dims[m, 0], dims[m, 1], cell[m]


@numba.njit(cache=True, inline="always")
def _greedy_ab(learner, q, q2, s) -> int:
    """The behaviour's greedy action: argmax Q, or argmax (A + B) for Double Q."""
    if learner != L_DOUBLE_Q:
        return greedy(q, s)
    return greedy_sum(q, q2, s)


@numba.njit(cache=True, inline="always")
def _behave(learner, q, q2, s, eps, rng) -> int:
    """Epsilon-greedy action (the draws of the Q-learning kernel)."""
    if rand01(rng) < eps:
        return randint(rng, N_ACTIONS)
    return _greedy_ab(learner, q, q2, s)


@numba.njit(cache=True)
def train_kernel(learner, q, q2, rng, ep, occ, occb, dims, cell, free, nfree, dist,
                 sectors, sensors, edges, which,
                 lr, lr_end, total_steps, gamma, eps_start, eps_end, eps_decay_steps, rw,
                 max_episode_steps, hold_max, guided, clear_r, max_seg, path, wps, rem, noise_mm,
                 lam, n_plan, model_s2, model_r, model_g, model_term, seen, n_seen, tr_s, tr_a, tr_e, tr,
                 start_step, n_steps, out_ret, out_succ, tw):
    """Advance exact sequential training by n_steps control periods of the robot `tw`.

    Epsilon follows `epsilon_at`; the learning rate falls linearly from lr to lr_end at
    total_steps (averaging out the noise that flips rarely visited, aliased states' actions). A chosen action is held while the state
    index stays the same, up to hold_max periods, and learnt as one semi-Markov transition
    (discount G = gamma^k, R the discounted sum): the greedy policy holds it anyway, so this is
    what the robot executes; hold_max = 1 is the plain one-step update.
    guided: episodes follow the planner's waypoints (`start_guidance`; wps/rem/path are the
    caller's buffers and carry the open episode across chunks). noise_mm > 0: the learner sees
    noisy readings (`noisy_encode_fast`), so the policy does not rely on a reading being exactly on one
    side of a range edge. occb: `bordered` copies of the maps (M, Hmax + 2, Wmax + 2).

    learner (L_*): the update at the end of a held action (s0, a) -> s2; q-learning's target is
    R + G * max_b Q(s2, b) (terminal: R; truncation bootstraps). The others are those of
    `ground_station.learn.cell.learners` with the discount G (`learn.jit`); sarsa and q-lambda
    draw the next action a2 at the update (ep[E_NEXT] = a2 + 1), expected-sarsa takes the next
    decision's epsilon. Writes one entry per finished episode to out_ret/out_succ; returns how many."""
    ranges = np.zeros(which.shape[0], dtype=np.int64)
    status = np.zeros(which.shape[0], dtype=np.int64)
    noisy = np.zeros(which.shape[0], dtype=np.int64)
    nstatus = np.zeros(which.shape[0], dtype=np.int64)
    n_done = 0
    b0 = 0.0
    og, ob, d, h, w, c = _episode_views(ep, occ, occb, dist, dims, cell)
    if ep[E_ACTIVE] != 0.0:  # the open episode's |bearing| (what its state was encoded with)
        kk = int(ep[E_WP])
        b0 = float(abs(bearing_mrad(ep[E_X], ep[E_Y], ep[E_TH], wps[kk, 0], wps[kk, 1])))
    for i in range(n_steps):
        t_glob = start_step + i
        if ep[E_ACTIVE] == 0.0:
            _new_episode(ep, rng, occ, dims, cell, free, nfree, dist, sectors, sensors, edges, which,
                         ranges, status, guided, clear_r, max_seg, path, wps, rem, tw)
            b0 = float(abs(bearing_mrad(ep[E_X], ep[E_Y], ep[E_TH], wps[0, 0], wps[0, 1])))
            ep[E_NEXT] = 0.0
            tr[0] = 0
            tr[1] = 0
            og, ob, d, h, w, c = _episode_views(ep, occ, occb, dist, dims, cell)
        s = int(ep[E_S])
        if ep[E_K] == 0.0:  # a decision: start a new option in state s
            if ep[E_NEXT] > 0.0:  # drawn at the last update (sarsa, q-lambda)
                a = int(ep[E_NEXT]) - 1
                ep[E_NEXT] = 0.0
            else:
                a = _behave(learner, q, q2, s, epsilon_at(t_glob, eps_start, eps_end, eps_decay_steps), rng)
            ep[E_A] = a
            ep[E_S0] = s
            ep[E_R] = 0.0
            ep[E_G] = 1.0
        a = int(ep[E_A])
        x, y, th, phi2, r, s2, hit, success, k, b1 = train_period(
            og, ob, h, w, c, d, ep[E_X], ep[E_Y], ep[E_TH], ep[E_PHI], b0, wps, rem, int(ep[E_NWP]),
            int(ep[E_WP]), a, rw, which, ranges, status, sectors, sensors, edges, guided, rng, noise_mm,
            noisy, nstatus, tw)
        ep[E_T] += 1.0
        ep[E_K] += 1.0
        terminal = hit or success
        if not terminal:
            ep[E_X] = x
            ep[E_Y] = y
            ep[E_TH] = th
            ep[E_PHI] = phi2
            ep[E_S] = s2
            ep[E_WP] = k
            b0 = b1
        else:
            s2 = s
        ep[E_R] += ep[E_G] * r
        ep[E_G] *= gamma
        ep[E_RET] += r
        end = terminal or ep[E_T] >= max_episode_steps
        if end or s2 != int(ep[E_S0]) or ep[E_K] >= hold_max:
            s0 = int(ep[E_S0])
            frac = min(1.0, (start_step + i) / total_steps) if total_steps > 0 else 0.0
            alpha = lr + (lr_end - lr) * frac
            big_r = ep[E_R]
            big_g = ep[E_G]
            if learner == L_Q:
                if terminal:
                    target = big_r
                else:  # also on truncation: bootstrap
                    target = big_r + big_g * q[s2, greedy(q, s2)]
                q[s0, a] += alpha * (target - q[s0, a])
            else:
                _other_update(learner, q, q2, rng, ep, s0, a, s2, big_r, big_g, terminal, end, alpha,
                              epsilon_at(t_glob + 1, eps_start, eps_end, eps_decay_steps), lam, n_plan,
                              model_s2, model_r, model_g, model_term, seen, n_seen, tr_s, tr_a, tr_e, tr)
            ep[E_K] = 0.0
        if end:
            out_ret[n_done] = ep[E_RET]
            out_succ[n_done] = success
            n_done += 1
            ep[E_ACTIVE] = 0.0
    return n_done


@numba.njit(cache=True)
def _other_update(learner, q, q2, rng, ep, s0, a, s2, big_r, big_g, terminal, end, alpha, eps_next, lam,
                  n_plan, model_s2, model_r, model_g, model_term, seen, n_seen, tr_s, tr_a, tr_e, tr):
    """The update of a held action (s0, a) -> s2 for the learners other than q
    (see `train_kernel`); eps_next: epsilon of the next decision."""
    a2 = 0
    draw = learner == L_SARSA or (learner == L_Q_LAMBDA and not end)  # sarsa's target needs it on truncation too
    if draw and not terminal:
        a2 = _behave(learner, q, q2, s2, eps_next, rng)
        if not end:
            ep[E_NEXT] = a2 + 1.0
    if learner == L_DOUBLE_Q:
        double_q_update(rng, q, q2, s0, a, big_r, s2, terminal, big_g, alpha)
    elif learner == L_Q_LAMBDA:
        q_lambda_update(q, s0, a, big_r, s2, a2, terminal, not end, big_g, alpha, lam, tr_s, tr_a, tr_e, tr)
    elif learner == L_DYNA_Q:
        dyna_q_update(rng, q, s0, a, big_r, s2, terminal, big_g, alpha, n_plan, model_s2, model_r, model_g,
                      model_term, seen, n_seen)
    else:
        target = big_r
        if not terminal:
            if learner == L_SARSA:
                target += big_g * q[s2, a2]
            else:  # expected-sarsa
                target += big_g * expected_value(q, s2, eps_next)
        q[s0, a] += alpha * (target - q[s0, a])


# evaluation outcomes
SUCCESS, COLLISION, LOOP, TIMEOUT = 0, 1, 2, 3


@numba.njit(cache=True)
def eval_kernel(q, occ, h, w, c, dists, starts, goals, goal_slot, headings, sectors, sensors, edges,
                which, max_steps, budget_base, budget_factor, stall_steps,
                guided, wp_all, nwp_all, rem_all, pair,
                out_outcome, out_path, out_steps, tw):
    """Greedy rollouts of episodes i = (starts[i], goals[i], headings[i]) from the start cell's
    centre (goal field dists[goal_slot[i]]; guided: waypoints wp_all[pair[i], :nwp_all[pair[i]]]).
    An episode ends on success, collision, loop (no new minimum of the guide potential for
    stall_steps periods) or timeout (max_steps if > 0, else budget_base + budget_factor x the
    shortest path in forward control periods)."""
    ranges = np.zeros(which.shape[0], dtype=np.int64)
    status = np.zeros(which.shape[0], dtype=np.int64)
    gwp = np.zeros((1, 2))
    grem = np.zeros(1)
    rw = np.zeros(6)
    for i in range(starts.shape[0]):
        d = dists[goal_slot[i]]
        x, y = cell_centre(starts[i, 0], starts[i, 1], h, c)
        gx, gy = cell_centre(goals[i, 0], goals[i, 1], h, c)
        if guided:
            wps = wp_all[pair[i]]
            rem = rem_all[pair[i]]
            nwp = nwp_all[pair[i]]
        else:
            gwp[0, 0] = gx
            gwp[0, 1] = gy
            wps = gwp
            rem = grem
            nwp = 1
        th = headings[i]
        if max_steps > 0:
            budget = max_steps
        else:
            budget = int(budget_base + budget_factor * d[starts[i, 1], starts[i, 0]] * c / tw[TW_GEO][G_FWD])
        k = 0
        phi = guide_potential(d, occ, h, w, c, x, y, wps, rem, k, guided)
        best = phi
        since = 0
        path = 0.0
        outcome = TIMEOUT
        t = 0
        sense(occ, h, w, c, x, y, th, which, ranges, status, tw)
        s = encode_fast(bearing_mrad(x, y, th, wps[k, 0], wps[k, 1]), ranges, status, sectors, sensors, edges)
        while t < budget:
            a = greedy(q, s)
            x, y, th, phi, _, s, hit, success, driven, k = period_step(
                occ, h, w, c, d, x, y, th, phi, wps, rem, nwp, k, a, rw, which, ranges, status,
                sectors, sensors, edges, guided, tw)
            path += driven
            t += 1
            if hit:
                outcome = COLLISION
                break
            if success:
                outcome = SUCCESS
                break
            if phi < best - 1.0:
                best = phi
                since = 0
            else:
                since += 1
                if since >= stall_steps:
                    outcome = LOOP
                    break
        out_outcome[i] = outcome
        out_path[i] = path
        out_steps[i] = t
