"""The `cell` kind's trainer, CleanRL style: read it top to bottom.

1. The numba kernel: exact sequential Q-learning on the `cell` encoding
   (one environment, one update per step, in order), the update

       Q(s, a) <- Q(s, a) + eta * (r + gamma * max_a' Q(s', a') - Q(s, a))

   with no bootstrap on termination (goal or collision), bootstrap on
   truncation, epsilon-greedy actions and a random goal and start every
   episode (the paper's protocol).
2. `CellProblem`: what the kernel needs, derived from a map and its goals.
3. `train_cell`: the kernel in chunks under a progress bar (the other learners:
   `learners`, same problem, schedule and rewards).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware_py.kinds.cell.encoder import CellEncoder
from ground_station.jitcache import numba
from ground_station.learn.config import TrainConfig
from ground_station.learn.envs.cell_env import (
    cell_transitions,
    goal_distances,
    reachable_starts,
    resolve_goals,
)
from ground_station.learn.jit import (
    cell_step,
    draw_episode_start,
    epsilon_at,
    greedy,
    rand01,
    seed_state,
)
from ground_station.learn.train import TrainResult, initial_table, run_in_chunks
from ground_station.maps import GridMap, MapError


# --- 1. the numba kernel ---------------------------------------------------
@numba.njit(cache=True, inline="always")
def cell_state(goal_index, cell, n_cells):
    """Jitted copy of `CellEncoder.encode` (cell = row * W + col; a test compares them)."""
    return goal_index * n_cells + cell


@numba.njit(cache=True, inline="always")
def q_update(q, s, a, r, s2, terminal, lr, gamma):
    """The update above; no bootstrap when `terminal` (goal or collision)."""
    target = r
    if not terminal:
        target += gamma * q[s2, greedy(q, s2)]
    q[s, a] += lr * (target - q[s, a])


@numba.njit(cache=True)
def q_learning_cell(q, next_cell, goal_cells, starts_flat, starts_off,
                    lr, gamma, eps_start, eps_end, eps_decay_steps,
                    r_goal, r_step, r_coll, max_ep_steps,
                    start_step, n_steps, rng, ep, ep_ret, out_ret, out_succ):
    """Advance training by `n_steps` steps from global step `start_step`. q: float64
    (n_goals*H*W, 4), updated in place. next_cell: (H*W, 4) from `cell_transitions`.
    starts_flat[starts_off[g]:starts_off[g+1]]: goal g's start cells. ep = [cell, goal, steps in
    episode, active] and ep_ret = [return] carry an unfinished episode across calls. Returns how
    many episodes finished (their returns/successes in out_ret/out_succ)."""
    n_goals = goal_cells.shape[0]
    n_cells = next_cell.shape[0]
    n_actions = q.shape[1]
    cell = ep[0]
    g = ep[1]
    t_ep = ep[2]
    active = ep[3]
    ret = ep_ret[0]
    n_done = 0
    for i in range(n_steps):
        if active == 0:
            g, cell = draw_episode_start(rng, n_goals, starts_flat, starts_off)
            t_ep = 0
            ret = 0.0
            active = 1
        t = start_step + i
        eps = epsilon_at(t, eps_start, eps_end, eps_decay_steps)
        s = cell_state(g, cell, n_cells)
        if rand01(rng) < eps:
            a = int(rand01(rng) * n_actions)
        else:
            a = greedy(q, s)
        c2 = next_cell[cell, a]
        t_ep += 1
        c2, r, done, success = cell_step(cell, c2, goal_cells[g], r_goal, r_step, r_coll)
        q_update(q, s, a, r, cell_state(g, c2, n_cells), done, lr, gamma)
        cell = c2
        ret += r
        if done or t_ep >= max_ep_steps:
            out_ret[n_done] = ret
            out_succ[n_done] = success
            n_done += 1
            active = 0
    ep[0] = cell
    ep[1] = g
    ep[2] = t_ep
    ep[3] = active
    ep_ret[0] = ret
    return n_done


# --- 2. the problem, 3. the training loop -----------------------------------
@dataclass
class CellProblem:
    """Everything the cell kernel needs, derived from a map and its goals."""

    gridmap: GridMap
    target_names: list[str]
    goals: list[tuple[int, int]]
    encoder: CellEncoder
    next_cell: np.ndarray
    goal_cells: np.ndarray
    starts_flat: np.ndarray
    starts_off: np.ndarray
    dist: np.ndarray

    @classmethod
    def build(cls, gridmap: GridMap, targets: str | list | None = None) -> CellProblem:
        names, goals = resolve_goals(gridmap, targets)
        dist = goal_distances(gridmap, goals)
        starts = reachable_starts(dist)
        for name, s in zip(names, starts, strict=True):
            if len(s) == 0:
                raise MapError(f"target {name} of map {gridmap.name} cannot be reached from any free cell")
        off = np.zeros(len(starts) + 1, dtype=np.int64)
        off[1:] = np.cumsum([len(s) for s in starts])
        w = gridmap.width
        return cls(gridmap, names, goals, CellEncoder(w, gridmap.height, len(goals)),
                   cell_transitions(gridmap.occ),
                   np.array([r * w + c for c, r in goals], dtype=np.int64),
                   np.concatenate(starts).astype(np.int64), off, dist)


def train_cell(cfg: TrainConfig, gridmap: GridMap, progress: bool = False) -> TrainResult:
    """Exact sequential Q-learning on the cell encoding (or `cfg.learner`'s, see 3. above)."""
    prob = CellProblem.build(gridmap, cfg.options.targets or None)
    q = initial_table(cfg, prob.encoder.n_states, prob.encoder.n_actions)
    meta = {"encoder": prob.encoder.to_dict(), "targets": prob.target_names,
            "goals": [list(g) for g in prob.goals], "learner": cfg.learner}
    if cfg.learner != "q":
        from ground_station.learn.cell.learners import DOUBLE_Q, CellLearner

        lrn = CellLearner(cfg, prob, q)
        rets, succs, secs = run_in_chunks(lambda _q, _done, n: lrn.run(n), q, cfg, progress,
                                          f"train cell {cfg.learner} {gridmap.name}")
        return TrainResult(lrn.table(), rets, succs, meta, secs, lrn.q2 if lrn.code == DOUBLE_Q else None)
    max_ep = cfg.max_episode_steps or gridmap.width * gridmap.height
    rng = seed_state(cfg.seed)
    ep = np.zeros(4, dtype=np.int64)
    ep_ret = np.zeros(1, dtype=np.float64)
    decay = int(cfg.epsilon_decay * cfg.steps)

    def run(q: np.ndarray, done: int, n: int) -> tuple[np.ndarray, np.ndarray]:
        out_ret = np.empty(n, dtype=np.float64)
        out_succ = np.empty(n, dtype=np.bool_)
        k = q_learning_cell(q, prob.next_cell, prob.goal_cells, prob.starts_flat, prob.starts_off,
                            cfg.lr, cfg.gamma, cfg.epsilon_start, cfg.epsilon_end, decay,
                            cfg.reward_goal, cfg.reward_step, cfg.reward_collision, max_ep,
                            done, n, rng, ep, ep_ret, out_ret, out_succ)
        return out_ret[:k], out_succ[:k]

    rets, succs, seconds = run_in_chunks(run, q, cfg, progress, f"train cell {gridmap.name}")
    return TrainResult(q, rets, succs, meta, seconds)
