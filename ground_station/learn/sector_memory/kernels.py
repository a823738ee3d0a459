"""The cell-stepped `sector-memory` encoding on a grid twin (numba): the jitted copy of
`GridBugEncoder` (a test compares them), its Q-learning kernel and greedy rollouts.

The twin moves the robot cell to cell: a relative move turns the reference
heading and drives one cell; a move into an obstacle cell or off the map is a
collision (it ends the episode: the bumper would stop the robot). The free
neighbours come from the occupancy grid (`free_world`); a test proves they are
the flags the reference encoder reads from the twin's range sensors.

`mem` = int64[4]: mode, side, hit distance (mm), reference heading, as
`GridBugMemory`. `params` = int64[4]: cell_mm, leave_margin_mm,
wall_bearing (0/1), wall_states.

Reward (training): `r_goal` on reaching the goal cell, `r_step` per move,
`r_coll` for a move into an obstacle (terminal); with `wall_rw` > 0 a
shaping cost in a wall mode when, after the move, the neighbour on the
followed side is free (the wall lost). A cost, not a bonus for keeping the
wall: a bonus above the step cost made circling a pillar for ever worth
more than the goal; with `go_rw` > 0 a shaping term in the go mode: `go_rw`
per cell the straight-line goal distance falls (what the robot knows: no map).
"""

from __future__ import annotations

import math

import numpy as np

from firmware_py.kinds.sector_memory import gridbug
from ground_station.jitcache import numba
from ground_station.learn.jit import epsilon_at, greedy, rand01, randint

MODE_GO = 0
MODE_WALL_RIGHT = 1
SUCCESS, COLLISION, TIMEOUT = 0, 1, 2
N_FREE = 16
N_SECTORS = 8
DCOL = np.array([1, 0, -1, 0], dtype=np.int64)  # world direction -> column step (east, north, west, south)
DROW = np.array([0, -1, 0, 1], dtype=np.int64)  # rows grow southwards
# (forward sign + 1) * 3 + (left sign + 1) -> sector (as firmware_py.kinds.sector_memory.gridbug._SECTOR)
SECTOR_OF = np.array([5, 4, 3, 6, 0, 2, 7, 0, 1], dtype=np.int64)


# the reference encoder's own frame rotation, jitted: one definition for the robot and the twin
rotate_into = numba.njit(cache=True, inline="always")(gridbug.rotate_into)


@numba.njit(cache=True, inline="always")
def sign_cell(v: int, cell: int) -> int:
    if 2 * v > cell:
        return 1
    if 2 * v < -cell:
        return -1
    return 0


@numba.njit(cache=True, inline="always")
def goalward_world(dx: int, dy: int, cell: int) -> int:
    sf = sign_cell(dx, cell)
    sl = sign_cell(dy, cell)
    return int(sf == 1) | int(sl == 1) << 1 | int(sf == -1) << 2 | int(sl == -1) << 3


@numba.njit(cache=True, inline="always")
def isqrt(n: int) -> int:
    """math.isqrt (numba has none): the float root corrected to the exact integer root."""
    r = int(math.sqrt(n))
    while r * r > n:
        r -= 1
    while (r + 1) * (r + 1) <= n:
        r += 1
    return r


@numba.njit(cache=True)
def gb_state(mem, dx: int, dy: int, free_world: int, params) -> int:
    """The jitted `GridBugEncoder.encode_free`: mode rules on `mem`, then the state index."""
    cell = params[0]
    dist = isqrt(dx * dx + dy * dy)
    gw = goalward_world(dx, dy, cell)
    if mem[0] != MODE_GO:
        if dist + params[1] <= mem[2] and (gw & free_world) != 0:
            mem[0] = MODE_GO
    elif gw != 0 and (gw & free_world) == 0:
        if mem[1] == 0:
            _, left = rotate_into(dx, dy, mem[3])
            mem[1] = 1 if left >= 0 else 2
        mem[0] = mem[1]
        mem[2] = dist
        g = 0
        for k in range(4):
            if (gw >> ((mem[3] + k) % 4)) & 1:
                g = (mem[3] + k) % 4
                break
        mem[3] = (g + 1) % 4 if mem[1] == MODE_WALL_RIGHT else (g + 3) % 4
    h = mem[3]
    free = 0
    for k in range(4):
        if (free_world >> ((h + k) % 4)) & 1:
            free |= 1 << k
    f, left = rotate_into(dx, dy, h)
    sector = SECTOR_OF[(sign_cell(f, cell) + 1) * 3 + sign_cell(left, cell) + 1]
    if mem[0] == MODE_GO:
        return sector * N_FREE + free
    w = sector * N_FREE + free if params[2] else free
    return N_SECTORS * N_FREE + (mem[0] - 1) * params[3] + w


@numba.njit(cache=True, inline="always")
def blocked(occ, h: int, w: int, col: int, row: int) -> bool:
    return col < 0 or row < 0 or col >= w or row >= h or occ[row, col] != 0


@numba.njit(cache=True)
def free_world(occ, h: int, w: int, col: int, row: int) -> int:
    """Bit d set when the neighbour in world direction d (east, north, west, south) is free."""
    m = 0
    for d in range(4):
        if not blocked(occ, h, w, col + DCOL[d], row + DROW[d]):
            m |= 1 << d
    return m


@numba.njit(cache=True, inline="always")
def goal_vector(col: int, row: int, gc: int, gr: int, cell: int):
    """Goal minus robot (mm, world frame, y north) between cell centres."""
    return (gc - col) * cell, (row - gr) * cell


@numba.njit(cache=True)
def _reset_mem(mem, heading: int) -> None:
    mem[0] = 0
    mem[1] = 0
    mem[2] = 0
    mem[3] = heading


@numba.njit(cache=True)
def train_kernel(q, rng, occs, dims, free_cells, nfree, bfs, params, lr, lr_end, total_steps, gamma,
                 eps_start, eps_end, eps_decay_steps, r_goal, r_step, r_coll, wall_rw, go_rw, max_episode_steps,
                 ep, mem, acc, start_step, n_steps, out_ret, out_succ):
    """Q-learning on the grid twin, `n_steps` moves from global step `start_step`.

    occs, dims, free_cells, nfree: maps packed as in `sector.kernels`; bfs (M, Fmax, Hmax, Wmax)
    int32 steps to each free cell (-1 unreachable).
    ep = int64[7]: active, map, col, row, goal index, steps, (unused); acc float64[1] the open
    episode's return (chunked calls equal one long call). Returns the number of finished
    episodes, their returns and successes in out_*."""
    n_done = 0
    m2 = np.empty(4, dtype=np.int64)
    for t in range(start_step, start_step + n_steps):
        if ep[0] == 0:
            m = randint(rng, occs.shape[0])
            nf = nfree[m]
            gi = randint(rng, nf)
            si = randint(rng, nf)
            while si == gi or bfs[m, gi, free_cells[m, si, 1], free_cells[m, si, 0]] < 0:
                si = randint(rng, nf)
            ep[0] = 1
            ep[1] = m
            ep[2] = free_cells[m, si, 0]
            ep[3] = free_cells[m, si, 1]
            ep[4] = gi
            ep[5] = 0
            _reset_mem(mem, randint(rng, 4))
            acc[0] = 0.0
        m = ep[1]
        h = dims[m, 0]
        w = dims[m, 1]
        occ = occs[m]
        col = ep[2]
        row = ep[3]
        gc = free_cells[m, ep[4], 0]
        gr = free_cells[m, ep[4], 1]
        dx, dy = goal_vector(col, row, gc, gr, params[0])
        s = gb_state(mem, dx, dy, free_world(occ, h, w, col, row), params)
        frac = t / total_steps if total_steps > 0 else 1.0
        alpha = lr + (lr_end - lr) * frac if lr_end >= 0.0 else lr
        eps = epsilon_at(t, eps_start, eps_end, eps_decay_steps)
        if rand01(rng) < eps:
            a = randint(rng, 4)
        else:
            a = greedy(q, s)
        mode = mem[0]
        side = mem[1]
        d = (mem[3] + a) % 4
        nc = col + DCOL[d]
        nr = row + DROW[d]
        ep[5] += 1
        done = False
        succ = False
        if blocked(occ, h, w, nc, nr):
            r = r_coll
            q[s, a] += alpha * (r - q[s, a])
            done = True
        else:
            mem[3] = d
            ep[2] = nc
            ep[3] = nr
            r = r_step
            if mode == MODE_GO and go_rw != 0.0:
                dx2, dy2 = goal_vector(nc, nr, gc, gr, params[0])
                r += go_rw * (math.sqrt(dx * dx + dy * dy) - math.sqrt(dx2 * dx2 + dy2 * dy2)) / params[0]
            if mode != MODE_GO and wall_rw != 0.0:
                sd = (d + 3) % 4 if side == MODE_WALL_RIGHT else (d + 1) % 4
                if not blocked(occ, h, w, nc + DCOL[sd], nr + DROW[sd]):
                    r -= wall_rw
            if nc == gc and nr == gr:
                r += r_goal
                q[s, a] += alpha * (r - q[s, a])
                done = True
                succ = True
            else:
                # the next decision's state applies the mode rules to a copy: the real update happens next step
                m2[:] = mem
                dx2, dy2 = goal_vector(nc, nr, gc, gr, params[0])
                s2 = gb_state(m2, dx2, dy2, free_world(occ, h, w, nc, nr), params)
                q[s, a] += alpha * (r + gamma * q[s2, greedy(q, s2)] - q[s, a])
                if ep[5] >= max_episode_steps:
                    done = True
        acc[0] += r
        if done:
            out_ret[n_done] = acc[0]
            out_succ[n_done] = succ
            n_done += 1
            ep[0] = 0
    return n_done


@numba.njit(cache=True)
def eval_kernel(q, occ, h, w, params, starts, goals, dirs, max_steps, outcome, moves, wall_moves, end_mode):
    """Greedy rollouts from (start cell, goal cell, initial grid direction): outcome, moves,
    moves in a wall mode, the mode at the end. The initial turn in place is not a move."""
    mem = np.zeros(4, dtype=np.int64)
    cell = params[0]
    for i in range(starts.shape[0]):
        col = starts[i, 0]
        row = starts[i, 1]
        gc = goals[i, 0]
        gr = goals[i, 1]
        _reset_mem(mem, dirs[i])
        res = TIMEOUT
        n = 0
        nw = 0
        while n < max_steps:
            dx, dy = goal_vector(col, row, gc, gr, cell)
            s = gb_state(mem, dx, dy, free_world(occ, h, w, col, row), params)
            a = greedy(q, s)
            if mem[0] != MODE_GO:
                nw += 1
            d = (mem[3] + a) % 4
            nc = col + DCOL[d]
            nr = row + DROW[d]
            n += 1
            if blocked(occ, h, w, nc, nr):
                res = COLLISION
                break
            mem[3] = d
            col = nc
            row = nr
            if col == gc and row == gr:
                res = SUCCESS
                break
        outcome[i] = res
        moves[i] = n
        wall_moves[i] = nw
        end_mode[i] = mem[0]
