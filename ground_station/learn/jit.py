"""Jitted helpers every training and evaluation kernel shares (numba).

Owns the random generator and the greedy choice, so the cell and sector
kernels draw the same kind of numbers and break ties the same way:

* xorshift64* whose state is a caller-owned uint64[1] array (seeded by
  splitmix64 in `seed_state`), so a run split into chunks draws exactly the
  numbers of one call: same seed -> same table;
* `greedy`: argmax of a Q row, ties to the lowest index, as the robot's
  `firmware_py.encoders.best_action`;
* `cell_step`: the grid world's reward and termination, so Q-learning and
  the other tabular learners score a move identically;
* `epsilon_at`: the linear exploration schedule every trainer follows.
"""

from __future__ import annotations

import numba
import numpy as np

_M12 = np.uint64(12)
_M25 = np.uint64(25)
_M27 = np.uint64(27)
_M11 = np.uint64(11)
_MUL = np.uint64(0x2545F4914F6CDD1D)
_INV53 = 1.0 / 9007199254740992.0


def seed_state(seed: int) -> np.ndarray:
    """A fresh generator state (uint64[1]) from an int seed, mixed by splitmix64."""
    z = (int(seed) + 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    z ^= z >> 31
    return np.array([z or 1], dtype=np.uint64)


@numba.njit(cache=True, inline="always")
def rand01(rng) -> float:
    """Uniform float in [0, 1) from the xorshift64* state `rng` (uint64[1])."""
    x = rng[0]
    x ^= x >> _M12
    x ^= x << _M25
    x ^= x >> _M27
    rng[0] = x
    return float((x * _MUL) >> _M11) * _INV53


@numba.njit(cache=True, inline="always")
def randint(rng, n: int) -> int:
    """Uniform int in [0, n)."""
    k = int(rand01(rng) * n)
    return k if k < n else n - 1


@numba.njit(cache=True, inline="always")
def greedy(q, s: int) -> int:
    """argmax of q[s]; ties break to the lowest index (as firmware best_action)."""
    best = 0
    bv = q[s, 0]
    for a in range(1, q.shape[1]):
        if q[s, a] > bv:
            bv = q[s, a]
            best = a
    return best


@numba.njit(cache=True, inline="always")
def cell_step(cell, c2, goal_cell, r_goal, r_step, r_coll):
    """The grid world's reward and termination for a move from `cell` whose
    transition table entry is `c2` (-1: into a wall or off the map): (next
    cell, reward, terminal, success). A collision is terminal and the robot
    stays; reaching the goal is terminal; otherwise the episode goes on
    (truncation by the step limit bootstraps: time limits are not terminal)."""
    if c2 < 0:
        return cell, r_coll, True, False
    if c2 == goal_cell:
        return c2, r_goal, True, True
    return c2, r_step, False, False


@numba.njit(cache=True, inline="always")
def epsilon_at(t, eps_start, eps_end, eps_decay_steps) -> float:
    """Linear epsilon schedule at global step t: eps_start -> eps_end over
    eps_decay_steps steps, then eps_end."""
    if eps_decay_steps > 0 and t < eps_decay_steps:
        return eps_start + (eps_end - eps_start) * (t / eps_decay_steps)
    return eps_end


@numba.njit(cache=True, inline="always")
def draw_episode_start(rng, n_goals, starts_flat, starts_off):
    """A cell-encoding episode's start: a uniform goal g, then a uniform cell of
    its start list starts_flat[starts_off[g]:starts_off[g + 1]]; returns
    (goal, start cell). Two uniform draws in that order, so every kernel that
    calls it replays the same episodes from the same seed."""
    g = int(rand01(rng) * n_goals)
    lo = starts_off[g]
    return g, starts_flat[lo + int(rand01(rng) * (starts_off[g + 1] - lo))]

