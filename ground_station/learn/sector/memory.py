"""The `sector-memory` encoding on the twin: jitted Bug-style memory, its
Q-learning kernel and greedy rollouts, in the direct setting (goal bearing
only, no waypoints).

* `memory_update_fast` is the jitted copy of the robot's reference
  `firmware_py.encoders.MemorySectorEncoder.update` (a test compares them on
  many inputs): GO -> wall-following when the front sensor is blocked with
  the goal ahead (side from the bearing's sign at the first hit of a goal,
  then kept), back to GO once the goal distance is `leave_margin_mm` below
  the hit distance. The state is mode * base states + the `SectorEncoder`
  index of `ground_station.learn.sector.twin.encode_fast`.
* `train_memory_kernel` is `ground_station.learn.sector.kernels.train_kernel`
  with that memory carried in the episode (`mem` = mode, side, hit distance)
  and `guided` fixed to 0: the same reward (`period_step`), semi-Markov holds,
  epsilon and learning-rate schedules and noisy readings. The memory sees
  the same (noisy) readings the state is encoded from, as on the robot.
  Reward: in the go mode `period_step`'s (progress along the goal's octile
  field), or with go_euclid the same terms with straight-line progress (no
  map knowledge: the go mode is meant to head for the goal and leave
  obstacles to the wall modes); in a wall mode its own task, wall following: wall_rw per cell of
  forward travel while the followed side's sensors see the wall within
  reach (`near_wall`), minus the step and reverse costs; the goal and
  collision terms are the same in every mode.
* `eval_memory_kernel` is `eval_kernel`'s greedy rollout with the memory;
  `eval_memory_diag` the same rollouts recording each episode's final mode
  and failure flags (F_CLOSER_BLOCKED, F_STUCK) for the failure classes.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from firmware_py import robot_spec
from firmware_py.encoders import turn_of
from ground_station.learn.jit import epsilon_at, greedy, rand01, randint
from ground_station.learn.sector.kernels import (
    COLLISION,
    E_A,
    E_ACTIVE,
    E_G,
    E_GOAL,
    E_GX,
    E_GY,
    E_K,
    E_MAP,
    E_PHI,
    E_R,
    E_RET,
    E_S,
    E_S0,
    E_T,
    E_TH,
    E_WP,
    E_X,
    E_Y,
    FWD_MM_PER_PERIOD,
    LOOP,
    REVERSE,
    SUCCESS,
    TIMEOUT,
    _new_episode,
    guide_potential,
    noisy_state,
    period_step,
)
from ground_station.learn.sector.reward import (
    RW_ALIGN,
    RW_GOAL,
    RW_PROGRESS,
    RW_REVERSE_COST,
    RW_STEP_COST,
)
from ground_station.learn.sector.twin import (
    bearing_mrad,
    bearing_sector_fast,
    cell_centre,
    encode_fast,
    sense,
)

MODE_GO = 0
MODE_WALL_RIGHT = 1
MODE_WALL_LEFT = 2
N_MODES = 3
HALF_TURN_MRAD = 3141  # TWO_PI_MRAD // 2 of the reference
TWO_PI_MRAD = 6283
M_MODE, M_SIDE, M_HIT, M_TURN = range(4)  # slots of the int64 memory array (BugMemory's fields)
MEM_LEN = 4
TURN_OF = np.array([turn_of(a) for a in range(len(robot_spec.ACTION_NAMES))], dtype=np.int64)


@numba.njit(cache=True)
def memory_update_fast(mem, bearing: int, dist_mm: int, ranges, status, block_mm: int,
                       block_bearing: int, leave_mm: int) -> int:
    """MemorySectorEncoder.update on mem (int64[3]: mode, side, hit mm) with
    all SENSOR_COUNT readings; returns the new mode."""
    r0 = ranges[0]
    st0 = status[0]
    if mem[M_MODE] == MODE_GO:
        b = (bearing + HALF_TURN_MRAD) % TWO_PI_MRAD - HALF_TURN_MRAD
        blocked = st0 == robot_spec.RANGE_TOO_CLOSE or (st0 == robot_spec.RANGE_VALID and r0 < block_mm)
        if abs(b) <= block_bearing and blocked:
            if mem[M_SIDE] == 0:
                mem[M_SIDE] = MODE_WALL_RIGHT if b >= 0 else MODE_WALL_LEFT
            mem[M_MODE] = mem[M_SIDE]
            mem[M_HIT] = dist_mm
    elif dist_mm + leave_mm <= mem[M_HIT]:
        i = bearing_sector_fast(bearing, robot_spec.SENSOR_COUNT)  # the sensor pointing nearest the goal
        if status[i] != robot_spec.RANGE_TOO_CLOSE and (status[i] != robot_spec.RANGE_VALID or ranges[i] >= block_mm):
            mem[M_MODE] = MODE_GO
    return mem[M_MODE]


@numba.njit(cache=True, inline="always")
def dist_mm(x: float, y: float, gx: float, gy: float) -> int:
    return int(math.floor(math.hypot(gx - x, gy - y) + 0.5))


@numba.njit(cache=True)
def memory_state(mem, base_state: int, n_base: int, x: float, y: float, th: float, gx: float, gy: float,
                 ranges, status, mp) -> int:
    """Update mem for the pose and return the memory state index (layout of
    MemorySectorEncoder.encode; n_base = bearing_sectors x R).
    mp = (block_mm, block_bearing_mrad, leave_margin_mm, bearing_sectors, R, wall reach mm, mode_states);
    mem[M_TURN] is the previous action's turn (set by the caller after each choice)."""
    mode = memory_update_fast(mem, bearing_mrad(x, y, th, gx, gy), dist_mm(x, y, gx, gy), ranges, status,
                              mp[0], mp[1], mp[2])
    s = base_state
    if mode != MODE_GO:
        s = (mp[3] + mode - 1) * mp[4] + base_state % mp[4]
    return mem[M_TURN] * mp[6] + s


@numba.njit(cache=True)
def near_wall(mode: int, ranges, status, reach_mm: int) -> bool:
    """The followed wall is in reach: the side sensor of the mode (right
    sensors 6, 7 for MODE_WALL_RIGHT, left 1, 2 for MODE_WALL_LEFT) reads
    too close or below reach_mm."""
    if mode == MODE_WALL_RIGHT:
        i, j = 6, 7
    else:
        i, j = 2, 1
    for s in (i, j):
        if status[s] == robot_spec.RANGE_TOO_CLOSE or (status[s] == robot_spec.RANGE_VALID and ranges[s] < reach_mm):
            return True
    return False


@numba.njit(cache=True)
def train_memory_kernel(q, rng, ep, mem, occ, dims, cell, free, nfree, dist,
                        sectors, sensors, edges, which, mp, n_base, wall_rw, wall_away, go_euclid,
                        lr, lr_end, total_steps, gamma, eps_start, eps_end, eps_decay_steps, rw,
                        max_episode_steps, hold_max, path, wps, rem, noise_mm,
                        start_step, n_steps, out_ret, out_succ):
    """`train_kernel` (direct) with the Bug memory in the state; see the module doc."""
    ranges = np.zeros(which.shape[0], dtype=np.int64)
    status = np.zeros(which.shape[0], dtype=np.int64)
    noisy = np.zeros(which.shape[0], dtype=np.int64)
    nstatus = np.zeros(which.shape[0], dtype=np.int64)
    n_done = 0
    for i in range(n_steps):
        if ep[E_ACTIVE] == 0.0:
            _new_episode(ep, rng, occ, dims, cell, free, nfree, dist, sectors, sensors, edges, which,
                         ranges, status, 0, 0.0, 0.0, path, wps, rem)
            mem[:] = 0
            ep[E_S] = memory_state(mem, int(ep[E_S]), n_base, ep[E_X], ep[E_Y], ep[E_TH], ep[E_GX], ep[E_GY],
                                   ranges, status, mp)
        s = int(ep[E_S])
        if ep[E_K] == 0.0:
            t_glob = start_step + i
            eps = epsilon_at(t_glob, eps_start, eps_end, eps_decay_steps)
            if rand01(rng) < eps:
                a = randint(rng, q.shape[1])
            else:
                a = greedy(q, s)
            ep[E_A] = a
            ep[E_S0] = s
            ep[E_R] = 0.0
            ep[E_G] = 1.0
        a = int(ep[E_A])
        mode0 = mem[M_MODE]
        mem[M_TURN] = TURN_OF[a]
        gx = wps[0, 0]
        gy = wps[0, 1]
        eu0 = math.hypot(ep[E_X] - gx, ep[E_Y] - gy)
        b0 = abs(bearing_mrad(ep[E_X], ep[E_Y], ep[E_TH], gx, gy))
        m = int(ep[E_MAP])
        h = dims[m, 0]
        w = dims[m, 1]
        c = cell[m]
        og = occ[m]
        d = dist[m, int(ep[E_GOAL])]
        x, y, th, phi2, r, s2, hit, success, drv, k = period_step(
            og, h, w, c, d, ep[E_X], ep[E_Y], ep[E_TH], ep[E_PHI], wps, rem, 1, 0, a, rw, which, ranges,
            status, sectors, sensors, edges, 0)
        terminal = hit or success
        if not hit and (mode0 != MODE_GO or go_euclid):
            r = -rw[RW_STEP_COST] - (rw[RW_REVERSE_COST] if a == REVERSE else 0.0)
            if success:
                r += rw[RW_GOAL]
            elif mode0 != MODE_GO:  # the wall modes' own reward: forward travel, full along the wall
                fwd = wall_rw * (-drv if a == REVERSE else drv) / c
                r += fwd if near_wall(mode0, ranges, status, mp[5]) else wall_away * fwd
            else:  # go mode, straight-line progress: head for the goal, the wall modes do the rest
                r += rw[RW_PROGRESS] * (eu0 - math.hypot(x - gx, y - gy)) / c
                r += rw[RW_ALIGN] * (b0 - abs(bearing_mrad(x, y, th, gx, gy))) / 3141.5927
        if not terminal:
            if noise_mm > 0.0:
                s2 = noisy_state(rng, noise_mm, x, y, th, wps[0, 0], wps[0, 1], ranges, status, noisy, nstatus,
                                 sectors, sensors, edges)
                s2 = memory_state(mem, s2, n_base, x, y, th, wps[0, 0], wps[0, 1], noisy, nstatus, mp)
            else:
                s2 = memory_state(mem, s2, n_base, x, y, th, wps[0, 0], wps[0, 1], ranges, status, mp)
        ep[E_T] += 1.0
        ep[E_K] += 1.0
        if not terminal:
            ep[E_X] = x
            ep[E_Y] = y
            ep[E_TH] = th
            ep[E_PHI] = phi2
            ep[E_S] = s2
            ep[E_WP] = k
        else:
            s2 = s
        ep[E_R] += ep[E_G] * r
        ep[E_G] *= gamma
        ep[E_RET] += r
        end = terminal or ep[E_T] >= max_episode_steps
        if end or s2 != int(ep[E_S0]) or ep[E_K] >= hold_max:
            s0 = int(ep[E_S0])
            if terminal:
                target = ep[E_R]
            else:
                target = ep[E_R] + ep[E_G] * q[s2, greedy(q, s2)]
            frac = min(1.0, (start_step + i) / total_steps) if total_steps > 0 else 0.0
            q[s0, a] += (lr + (lr_end - lr) * frac) * (target - q[s0, a])
            ep[E_K] = 0.0
        if end:
            out_ret[n_done] = ep[E_RET]
            out_succ[n_done] = success
            n_done += 1
            ep[E_ACTIVE] = 0.0
    return n_done


# Failure flags of `eval_memory_diag` (out_flags bits).
F_CLOSER_BLOCKED = 1  # in a wall mode the goal came leave_margin closer than the hit, but the goal-ward sensor was blocked
F_STUCK = 2  # the last STUCK_WINDOW periods of a failed episode moved the centre less than STUCK_MM
STUCK_WINDOW = 200
STUCK_MM = 100.0


@numba.njit(cache=True)
def eval_memory_kernel(q, occ, h, w, c, dists, starts, goals, goal_slot, headings, sectors, sensors, edges,
                       which, mp, n_base, max_steps, budget_base, budget_factor, stall_steps,
                       out_outcome, out_path, out_steps, out_mode_steps):
    """Greedy rollouts as `eval_kernel` (direct) with the Bug memory; also
    counts the periods spent in a wall-following mode (out_mode_steps)."""
    n = starts.shape[0]
    eval_memory_diag(q, occ, h, w, c, dists, starts, goals, goal_slot, headings, sectors, sensors, edges,
                     which, mp, n_base, max_steps, budget_base, budget_factor, stall_steps,
                     out_outcome, out_path, out_steps, out_mode_steps,
                     np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64))


@numba.njit(cache=True)
def eval_memory_diag(q, occ, h, w, c, dists, starts, goals, goal_slot, headings, sectors, sensors, edges,
                     which, mp, n_base, max_steps, budget_base, budget_factor, stall_steps,
                     out_outcome, out_path, out_steps, out_mode_steps, out_end_mode, out_flags):
    """`eval_memory_kernel` that also records, per episode, the mode at the
    end (out_end_mode: the mode the last action was chosen in) and the
    failure flags F_CLOSER_BLOCKED / F_STUCK (out_flags): what
    `evaluate_memory` classifies the failures by."""
    trail = np.zeros((STUCK_WINDOW, 2))
    ranges = np.zeros(which.shape[0], dtype=np.int64)
    status = np.zeros(which.shape[0], dtype=np.int64)
    wps = np.zeros((1, 2))
    rem = np.zeros(1)
    rw = np.zeros(6)
    mem = np.zeros(MEM_LEN, dtype=np.int64)
    for i in range(starts.shape[0]):
        d = dists[goal_slot[i]]
        x, y = cell_centre(starts[i, 0], starts[i, 1], h, c)
        gx, gy = cell_centre(goals[i, 0], goals[i, 1], h, c)
        wps[0, 0] = gx
        wps[0, 1] = gy
        th = headings[i]
        if max_steps > 0:
            budget = max_steps
        else:
            budget = int(budget_base + budget_factor * d[starts[i, 1], starts[i, 0]] * c / FWD_MM_PER_PERIOD)
        phi = guide_potential(d, occ, h, w, c, x, y, wps, rem, 0, 0)
        best = phi
        since = 0
        path = 0.0
        outcome = TIMEOUT
        t = 0
        wall = 0
        flags = 0
        mode_at = 0
        mem[:] = 0
        sense(occ, h, w, c, x, y, th, which, ranges, status)
        s = encode_fast(bearing_mrad(x, y, th, gx, gy), ranges, status, sectors, sensors, edges)
        s = memory_state(mem, s, n_base, x, y, th, gx, gy, ranges, status, mp)
        while t < budget:
            trail[t % STUCK_WINDOW, 0] = x
            trail[t % STUCK_WINDOW, 1] = y
            mode_at = mem[M_MODE]
            if mode_at != MODE_GO and dist_mm(x, y, gx, gy) + mp[2] <= mem[M_HIT]:
                flags |= F_CLOSER_BLOCKED  # still in the wall mode: the goal-ward sensor kept it there
            a = greedy(q, s)
            mem[M_TURN] = TURN_OF[a]
            x, y, th, phi, _, s, hit, success, driven, _k = period_step(
                occ, h, w, c, d, x, y, th, phi, wps, rem, 1, 0, a, rw, which, ranges, status,
                sectors, sensors, edges, 0)
            path += driven
            t += 1
            if hit:
                outcome = COLLISION
                break
            if success:
                outcome = SUCCESS
                break
            s = memory_state(mem, s, n_base, x, y, th, gx, gy, ranges, status, mp)
            if mem[M_MODE] != MODE_GO:
                wall += 1
            if phi < best - 1.0:
                best = phi
                since = 0
            else:
                since += 1
                if since >= stall_steps:
                    outcome = LOOP
                    break
        if outcome != SUCCESS and outcome != COLLISION and t >= STUCK_WINDOW:
            j = t % STUCK_WINDOW  # the oldest pose of the window
            if math.hypot(x - trail[j, 0], y - trail[j, 1]) < STUCK_MM:
                flags |= F_STUCK
        out_outcome[i] = outcome
        out_path[i] = path
        out_steps[i] = t
        out_mode_steps[i] = wall
        out_end_mode[i] = mode_at
        out_flags[i] = flags
