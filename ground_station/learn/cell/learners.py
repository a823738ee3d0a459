"""Tabular learners beside Q-learning on the `cell` encoding, CleanRL style.

One numba kernel, `td_cell`, with a switch (`learner`, its index in `LEARNERS`)
over six algorithms that share everything else with `q_learning_cell`; with
learner = q it reproduces `q_learning_cell` bit for bit (a test checks it).

The next action a' is drawn before the current step's update (SARSA's target
and Q(lambda)'s trace cut need it; s' != s on every non-terminal step, so for
the one-step learners this equals drawing it after), and only when the
episode continues (SARSA also on truncation), so learner q draws the numbers
of `q_learning_cell`.

Targets (terminal: r alone):

* q:               r + gamma * max_b Q(s', b)
* sarsa:           r + gamma * Q(s', a')
* expected-sarsa:  r + gamma * sum_b pi(b | s') Q(s', b), pi = epsilon-greedy
                   at the current epsilon (ties: greedy = lowest index)
* double-q:        two tables A and B (van Hasselt 2010); a coin picks which
                   one learns: A(s,a) toward r + gamma * B(s', argmax_b A(s', b));
                   the behaviour acts greedily on A + B; the run's table is
                   (A + B) / 2.
* dyna-q:          Q-learning plus `dyna_planning` updates per real step from
                   the last seen s', r, terminal per (s, a) (the world is
                   deterministic), drawn uniformly among the pairs seen.
* q-lambda:        Watkins' Q(lambda): delta = r + gamma * max_b Q(s', b) - Q(s, a),
                   every traced pair moves by lr * delta * e, traces decay by
                   gamma * lambda and are cut when a' is exploratory (not greedy
                   at s'). Accumulating traces in a ring of the episode's recent
                   pairs: one older than log(trace_min) / log(gamma * lambda)
                   steps has e < trace_min and is dropped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ground_station.jitcache import numba
from ground_station.learn.config import LEARNERS, TrainConfig
from ground_station.learn.jit import (
    cell_step,
    double_q_update,
    draw_episode_start,
    dyna_q_update,
    epsilon_at,
    expected_value,
    greedy,
    greedy_sum,
    q_lambda_update,
    rand01,
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


@numba.njit(cache=True)
def td_cell(learner, qa, qb, next_cell, goal_cells, starts_flat, starts_off,
            lr, gamma, eps_start, eps_end, eps_decay_steps,
            r_goal, r_step, r_coll, max_ep_steps, lam, n_plan,
            model_s2, model_r, model_g, model_term, seen, n_seen,
            tr_s, tr_a, tr_e, tr,
            start_step, n_steps, rng, ep, ep_ret, out_ret, out_succ):
    """`q_learning_cell` for every learner; qb: Double Q's second table (else unused), model_*,
    seen, n_seen: Dyna-Q's model, tr_*: Q(lambda)'s trace ring (`LearnerMemory`); ep = [cell,
    goal, steps in episode, active, a] carries an unfinished episode and its next action."""
    n_goals = goal_cells.shape[0]
    n_cells = next_cell.shape[0]
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
        elif learner == DYNA_Q:
            dyna_q_update(rng, qa, s, a, r, s2, done, gamma, lr, n_plan, model_s2, model_r, model_g, model_term,
                          seen, n_seen)
        else:
            target = r
            if not done:
                if learner == SARSA:
                    target += gamma * qa[s2, a2]
                elif learner == EXPECTED_SARSA:
                    target += gamma * expected_value(qa, s2, eps)
                else:  # q
                    target += gamma * qa[s2, greedy(qa, s2)]
            qa[s, a] += lr * (target - qa[s, a])
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
    """Dyna-Q's model (`dyna_q_update`; the discount is the sector's semi-Markov gamma^k) and
    Q(lambda)'s trace ring (tr = [head, length]), sized for the learner that uses them (1-element
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
    """One learner's state on a `CellProblem` (tables, model or traces, generator, open episode)."""

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
                    c.dyna_planning, m.model_s2, m.model_r, m.model_g, m.model_term, m.seen, m.n_seen,
                    m.tr_s, m.tr_a, m.tr_e, m.tr,
                    self.done, n, self.rng, self.ep, self.ep_ret, out_ret, out_succ)
        self.done += n
        return out_ret[:k].copy(), out_succ[:k].copy()

    def table(self) -> np.ndarray:
        """The run's greedy table: Q, or (A + B) / 2 for Double Q."""
        return (self.q + self.q2) / 2.0 if self.code == DOUBLE_Q else self.q
