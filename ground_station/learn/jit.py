"""Jitted helpers every training and evaluation kernel shares (numba).

* xorshift64* whose state is a caller-owned uint64[1] array (seeded by
  splitmix64 in `seed_state`), so a run split into chunks draws exactly the
  numbers of one call: same seed -> same table;
* `greedy`: argmax of a Q row, ties to the lowest index, as the robot's
  `best_action` (`greedy_sum`: of two tables' sum);
* `cell_step`, `epsilon_at`: the grid world's reward and termination, the
  linear exploration schedule;
* `double_q_update`, `q_lambda_update`, `dyna_q_update`, `expected_value`: the
  learners' updates (the sector kernel's discount is gamma^k for an action held
  k periods, the cell kernel's gamma).
"""

from __future__ import annotations

import numpy as np

from ground_station.jitcache import numba

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
def greedy_sum(qa, qb, s: int) -> int:
    """argmax of qa[s] + qb[s], ties to the lowest index: Double Q's behaviour acts on both tables."""
    best = 0
    bv = qa[s, 0] + qb[s, 0]
    for a in range(1, qa.shape[1]):
        v = qa[s, a] + qb[s, a]
        if v > bv:
            bv = v
            best = a
    return best


@numba.njit(cache=True, inline="always")
def cell_step(cell, c2, goal_cell, r_goal, r_step, r_coll):
    """The grid world's (next cell, reward, terminal, success) for a move from `cell` to
    transition table entry `c2` (-1: a collision, the robot stays). Goal and collision are
    terminal; the step limit is not (truncation bootstraps)."""
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
    """A cell-encoding episode's (goal, start cell): a uniform goal g, then a uniform cell of
    starts_flat[starts_off[g]:starts_off[g + 1]], so every kernel replays the same episodes."""
    g = int(rand01(rng) * n_goals)
    lo = starts_off[g]
    return g, starts_flat[lo + int(rand01(rng) * (starts_off[g + 1] - lo))]


@numba.njit(cache=True, inline="always")
def double_q_update(rng, qa, qb, s: int, a: int, r: float, s2: int, terminal: bool, discount: float,
                    lr: float) -> None:
    """Double Q-learning's update of (s, a) -> s2: a coin picks the table that
    learns; the other one values the learning table's greedy next action."""
    if rand01(rng) < 0.5:
        learn, other = qa, qb
    else:
        learn, other = qb, qa
    target = r
    if not terminal:
        target += discount * other[s2, greedy(learn, s2)]
    learn[s, a] += lr * (target - learn[s, a])


@numba.njit(cache=True, inline="always")
def dyna_q_update(rng, q, s: int, a: int, r: float, s2: int, terminal: bool, discount: float, lr: float,
                  n_plan: int, model_s2, model_r, model_g, model_term, seen, n_seen) -> None:
    """Dyna-Q's Q-learning update of (s, a) -> s2, recorded in the model (keys s * n_actions + a:
    the last s2, reward, discount, terminal; seen[:n_seen[0]] the keys seen), then n_plan updates
    of uniformly drawn seen pairs."""
    target = r
    if not terminal:
        target += discount * q[s2, greedy(q, s2)]
    q[s, a] += lr * (target - q[s, a])
    key = s * q.shape[1] + a
    if model_s2[key] < 0:
        seen[n_seen[0]] = key
        n_seen[0] += 1
    model_s2[key] = s2
    model_r[key] = r
    model_g[key] = discount
    model_term[key] = terminal
    for _ in range(n_plan):
        key = seen[randint(rng, n_seen[0])]
        ps = key // q.shape[1]
        pa = key % q.shape[1]
        pt = model_r[key]
        if not model_term[key]:
            pt += model_g[key] * q[model_s2[key], greedy(q, model_s2[key])]
        q[ps, pa] += lr * (pt - q[ps, pa])


@numba.njit(cache=True, inline="always")
def q_lambda_update(q, s: int, a: int, r: float, s2: int, a2: int, terminal: bool, goes_on: bool,
                    discount: float, lr: float, lam: float, tr_s, tr_a, tr_e, tr) -> None:
    """Watkins's Q(lambda) update of (s, a) -> s2 over the trace ring
    tr_s/tr_a/tr_e (tr = [head, length]); a2 is the behaviour's next action,
    which cuts the traces when the episode `goes_on` with an exploratory one."""
    cap = tr_s.shape[0]
    a_star = greedy(q, s2)
    target = r
    if not terminal:
        target += discount * q[s2, a_star]
    delta = target - q[s, a]
    k = (tr[0] + tr[1]) % cap  # push (s, a) with e = 1 (accumulating: a revisit is a second entry)
    if tr[1] == cap:
        tr[0] = (tr[0] + 1) % cap  # the oldest entry's e < trace_min: dropped
    else:
        tr[1] += 1
    tr_s[k] = s
    tr_a[k] = a
    tr_e[k] = 1.0
    exploratory = goes_on and q[s2, a2] < q[s2, a_star]  # before the traces change q
    decay = discount * lam
    for j in range(tr[1]):
        m = (tr[0] + j) % cap
        q[tr_s[m], tr_a[m]] += lr * delta * tr_e[m]
        tr_e[m] *= decay
    if exploratory:  # the greedy chain is broken, cut the traces
        tr[0] = 0
        tr[1] = 0


@numba.njit(cache=True, inline="always")
def expected_value(q, s: int, eps: float) -> float:
    """Expected SARSA's value of state s under the epsilon-greedy policy on q."""
    n = q.shape[1]
    b = greedy(q, s)
    v = 0.0
    for k in range(n):
        v += q[s, k]
    return (eps / n) * v + (1.0 - eps) * q[s, b]
