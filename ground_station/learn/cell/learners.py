"""Tabular learners beside Q-learning on the `cell` encoding, CleanRL style.

One numba kernel, `td_cell`, with a documented switch (`learner`, the index
of `TrainConfig.learner` in `LEARNERS`) over six algorithms that share
everything else with the Q-learning kernel of `ground_station.learn.train`:
the transition table, the random goal and start per episode, the linear
epsilon schedule, the rewards, termination (goal, collision: no bootstrap)
and truncation (bootstrap), and the xorshift generator (same seed -> same
table, regardless of chunking). With learner = q it reproduces
`q_learning_cell` bit for bit (a test checks it).

The next action a' is drawn (epsilon-greedy, behaviour policy) before the
current step's update: SARSA needs it in its target and Watkins' Q(lambda)
needs it to decide whether to cut the traces. In the cell world s' != s on
every non-terminal step, so for the one-step learners this equals drawing
it after the update. It is drawn only when the episode continues (SARSA
also draws it on truncation, where its target needs it), so the random
stream of learner q is that of `q_learning_cell`.

Targets (terminal: r alone):

* q:               r + gamma * max_b Q(s', b)
* sarsa:           r + gamma * Q(s', a')
* expected-sarsa:  r + gamma * sum_b pi(b | s') Q(s', b), pi = epsilon-greedy
                   at the current epsilon (ties: greedy = lowest index)
* double-q:        two tables A and B (van Hasselt 2010); a coin picks which
                   one learns: A(s,a) toward r + gamma * B(s', argmax_b A(s', b))
                   (or B toward A's value of B's argmax); the behaviour acts
                   greedily on A + B; the run's table is (A + B) / 2 (same
                   greedy actions).
* dyna-q:          Q-learning plus `dyna_planning` simulated updates per real
                   step from a learnt model (the world is deterministic: the
                   model stores the last seen s', r, terminal per (s, a));
                   planning draws uniformly among the (s, a) pairs seen so far.
* q-lambda:        Watkins' Q(lambda): delta = r + gamma * max_b Q(s', b) - Q(s, a),
                   every traced pair moves by lr * delta * e, traces decay by
                   gamma * lambda and are cut (emptied) when a' is exploratory
                   (not greedy at s'). Accumulating traces, kept as a ring of
                   the episode's recent pairs: a pair older than
                   log(trace_min) / log(gamma * lambda) steps has e < trace_min
                   and is dropped.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numba
import numpy as np

from ground_station.learn.config import LEARNERS, TrainConfig
from ground_station.learn.jit import (
    cell_step,
    double_q_update,
    draw_episode_start,
    epsilon_at,
    expected_value,
    greedy,
    greedy_sum,
    q_lambda_update,
    rand01,
    randint,
    seed_state,
)

Q, SARSA, EXPECTED_SARSA, DOUBLE_Q, DYNA_Q, Q_LAMBDA = range(6)
assert LEARNERS == ("q", "sarsa", "expected-sarsa", "double-q", "dyna-q", "q-lambda")


@numba.njit(cache=True, inline="always")
def _act(learner, qa, qb, s, eps, rng):
    """Epsilon-greedy behaviour action (Double Q: greedy on A + B)."""
    if rand01(rng) < eps:
        return int(rand01(rng) * qa.shape[1])
    if learner == DOUBLE_Q:
        return greedy_sum(qa, qb, s)
    return greedy(qa, s)


@numba.njit(cache=True, inline="always")
def _max(q, s):
    m = q[s, 0]
    for k in range(1, q.shape[1]):
        if q[s, k] > m:
            m = q[s, k]
    return m


@numba.njit(cache=True)
def td_cell(learner, qa, qb, next_cell, goal_cells, starts_flat, starts_off,
            lr, gamma, eps_start, eps_end, eps_decay_steps,
            r_goal, r_step, r_coll, max_ep_steps, lam, n_plan,
            model_s2, model_r, model_term, seen, n_seen,
            tr_s, tr_a, tr_e, tr,
            start_step, n_steps, rng, ep, ep_ret, out_ret, out_succ):
    """Advance training by `n_steps` steps from global step `start_step`.

    qa: the table (n_goals*H*W, 4); qb: Double Q's second table (else unused).
    model_s2/model_r/model_term (n_states*4, s2 = -1 unseen), seen[:n_seen[0]]
    (keys s*4+a): Dyna-Q's model. tr_s/tr_a/tr_e: Q(lambda)'s trace ring,
    tr = [head, length]. ep = [cell, goal, steps in episode, active, a]
    carries an unfinished episode (and its next action) across calls.
    Returns how many episodes finished (their returns/successes in out_*)."""
    n_goals = goal_cells.shape[0]
    n_cells = next_cell.shape[0]
    n_actions = qa.shape[1]
    cell = ep[0]
    g = ep[1]
    t_ep = ep[2]
    active = ep[3]
    a = ep[4]
    ret = ep_ret[0]
    n_done = 0
    for i in range(n_steps):
        t = start_step + i
        eps = epsilon_at(t, eps_start, eps_end, eps_decay_steps)
        if active == 0:
            g, cell = draw_episode_start(rng, n_goals, starts_flat, starts_off)
            t_ep = 0
            ret = 0.0
            active = 1
            tr[0] = 0
            tr[1] = 0
            a = _act(learner, qa, qb, g * n_cells + cell, eps, rng)
        s = g * n_cells + cell
        c2 = next_cell[cell, a]
        t_ep += 1
        c2, r, done, success = cell_step(cell, c2, goal_cells[g], r_goal, r_step, r_coll)
        truncated = not done and t_ep >= max_ep_steps
        s2 = g * n_cells + c2
        # the next action (behaviour policy), before this step's update
        a2 = 0
        if not done and (not truncated or learner == SARSA):
            t2 = t + 1
            eps2 = epsilon_at(t2, eps_start, eps_end, eps_decay_steps)
            a2 = _act(learner, qa, qb, s2, eps2, rng)

        if learner == DOUBLE_Q:
            double_q_update(rng, qa, qb, s, a, r, s2, done, gamma, lr)
        elif learner == Q_LAMBDA:
            q_lambda_update(qa, s, a, r, s2, a2, done, not done and not truncated, gamma, lr, lam,
                            tr_s, tr_a, tr_e, tr)
        else:
            target = r
            if not done:
                if learner == SARSA:
                    target += gamma * qa[s2, a2]
                elif learner == EXPECTED_SARSA:
                    target += gamma * expected_value(qa, s2, eps)
                else:  # q, dyna-q
                    target += gamma * _max(qa, s2)
            qa[s, a] += lr * (target - qa[s, a])
            if learner == DYNA_Q:
                key = s * n_actions + a
                if model_s2[key] < 0:
                    seen[n_seen[0]] = key
                    n_seen[0] += 1
                model_s2[key] = s2
                model_r[key] = r
                model_term[key] = done
                for _ in range(n_plan):
                    key = seen[randint(rng, n_seen[0])]
                    ps = key // n_actions
                    pa = key % n_actions
                    pt = model_r[key]
                    if not model_term[key]:
                        pt += gamma * _max(qa, model_s2[key])
                    qa[ps, pa] += lr * (pt - qa[ps, pa])
        cell = c2
        a = a2
        ret += r
        if done or truncated:
            out_ret[n_done] = ret
            out_succ[n_done] = success
            n_done += 1
            active = 0
    ep[0] = cell
    ep[1] = g
    ep[2] = t_ep
    ep[3] = active
    ep[4] = a
    ep_ret[0] = ret
    return n_done


def trace_capacity(cfg: TrainConfig, max_ep: int) -> int:
    """Ring length of Q(lambda)'s traces: steps until (gamma * lambda)^k < trace_min,
    at most one episode."""
    gl = cfg.gamma * cfg.learner_lambda
    if gl <= 0.0:
        return 1
    if gl >= 1.0:
        return max_ep
    return max(1, min(max_ep, math.ceil(math.log(cfg.trace_min) / math.log(gl)) + 1))


@dataclass
class LearnerMemory:
    """Dyna-Q's learnt model (keys s * n_actions + a: next state, -1 unseen; reward; discount, the
    sector's semi-Markov gamma^k; terminal; the keys seen) and Q(lambda)'s trace ring (states,
    actions, traces; tr = [head, length]), sized for the learner that uses them (1-element
    dummies otherwise). The cell and sector kernels take them as arrays."""

    model_s2: np.ndarray
    model_r: np.ndarray
    model_g: np.ndarray
    model_term: np.ndarray
    seen: np.ndarray
    n_seen: np.ndarray
    tr_s: np.ndarray
    tr_a: np.ndarray
    tr_e: np.ndarray
    tr: np.ndarray

    @classmethod
    def make(cls, cfg: TrainConfig, code: int, n_states: int, n_actions: int, max_ep: int) -> LearnerMemory:
        nk = n_states * n_actions if code == DYNA_Q else 1
        cap = trace_capacity(cfg, max_ep) if code == Q_LAMBDA else 1
        return cls(np.full(nk, -1, dtype=np.int64), np.zeros(nk), np.zeros(nk), np.zeros(nk, dtype=np.bool_),
                   np.zeros(nk, dtype=np.int64), np.zeros(1, dtype=np.int64), np.zeros(cap, dtype=np.int64),
                   np.zeros(cap, dtype=np.int64), np.zeros(cap), np.zeros(2, dtype=np.int64))


class CellLearner:
    """One learner's state on a `CellProblem`: the table(s), the model or traces,
    the generator and the unfinished episode; `run(n)` advances n steps."""

    def __init__(self, cfg: TrainConfig, prob, q: np.ndarray) -> None:
        self.cfg = cfg
        self.prob = prob
        self.code = LEARNERS.index(cfg.learner)
        self.q = q
        n_states, n_actions = q.shape
        # Double Q's second table starts where A starts (zeros or the same random init)
        self.q2 = q.copy() if self.code == DOUBLE_Q else np.zeros((1, n_actions))
        self.max_ep = cfg.max_episode_steps or prob.gridmap.width * prob.gridmap.height
        self.mem = LearnerMemory.make(cfg, self.code, n_states, n_actions, self.max_ep)
        self.rng = seed_state(cfg.seed)
        self.ep = np.zeros(5, dtype=np.int64)
        self.ep_ret = np.zeros(1, dtype=np.float64)
        self.decay = int(cfg.epsilon_decay * cfg.steps)
        self.done = 0

    def run(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Advance n steps; the returns and successes of the episodes that finished."""
        c, p, m = self.cfg, self.prob, self.mem
        out_ret = np.empty(n, dtype=np.float64)
        out_succ = np.empty(n, dtype=np.bool_)
        k = td_cell(self.code, self.q, self.q2, p.next_cell, p.goal_cells, p.starts_flat, p.starts_off,
                    c.lr, c.gamma, c.epsilon_start, c.epsilon_end, self.decay,
                    c.reward_goal, c.reward_step, c.reward_collision, self.max_ep, c.learner_lambda,
                    c.dyna_planning, m.model_s2, m.model_r, m.model_term, m.seen, m.n_seen,
                    m.tr_s, m.tr_a, m.tr_e, m.tr,
                    self.done, n, self.rng, self.ep, self.ep_ret, out_ret, out_succ)
        self.done += n
        return out_ret[:k].copy(), out_succ[:k].copy()

    def table(self) -> np.ndarray:
        """The run's greedy table: Q, or (A + B) / 2 for Double Q."""
        return (self.q + self.q2) / 2.0 if self.code == DOUBLE_Q else self.q


def train_cell_learner(cfg: TrainConfig, prob, q: np.ndarray, progress_bar=None):
    """Train `cfg.learner` on a CellProblem in chunks; (table, second table or None,
    returns, successes, seconds)."""
    lrn = CellLearner(cfg, prob, q)
    chunk = min(cfg.chunk_steps, cfg.steps)
    rets, succs = [], []
    t0 = time.perf_counter()
    while lrn.done < cfg.steps:
        n = min(chunk, cfg.steps - lrn.done)
        r, s = lrn.run(n)
        rets.append(r)
        succs.append(s)
        if progress_bar is not None:
            progress_bar.update(n)
    seconds = time.perf_counter() - t0
    q2 = lrn.q2 if lrn.code == DOUBLE_Q else None
    return lrn.table(), q2, np.concatenate(rets), np.concatenate(succs), seconds
