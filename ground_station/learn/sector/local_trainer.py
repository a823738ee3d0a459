"""Q-learning of the sector follower on the local planner's sub-goals; read it top to bottom.

The robot steers its sector table on `firmware_py.localplan`'s targets: the
current waypoint until an obstacle the map does not know is in the way, then
a sub-goal round it. The shipped table was learnt without obstacles and
steering on waypoints only. This module re-learns it (tabular Q-learning,
the paper's method) in the loop the bench rolls it out in
(`ground_station.nav.planned.rollout`): per control period

1. `ObstacleMemory.observe` with the readings at the twin's pose, then
   `LocalPlanner.target` for the current waypoint (reset per waypoint);
2. the state = the sector encoding of the bearing to that target and the
   range readings (Gaussian noise on them, as the shipped trainer);
3. the physics, movers and sensing of `learn.sector.obstacles.obs_period_step`
   (all eight sensors read);
4. the reward of the period: progress toward the target of step 1 (distance
   before minus after, per cell, as `SectorReward` scales it), the bearing
   alignment term toward that target, a cost per reverse period, the goal
   bonus, and -collision (terminal) on contact; optionally a cost per
   period while the guide potential has made no new minimum for
   `stall_free` periods, and a terminal penalty when the episode stalls for
   the bench's `stall_steps` (its loop rule).

Actions are held while the state is unchanged (up to `hold_max` periods) and
updated as one semi-Markov step, as the shipped trainer
(`obstacles.held_update`) does, so the start table's values keep their scale.
Episodes come from a seeded pool of scenario episodes
(`obstacle_trainer.scenario_pool`) on the TRAINING maps only (`TRAIN_MAPS`:
paper10 and the -s0 generated maps; the bench's maps are the -s1 ones), 0..k_max
discs and 0..m_max movers each, so some episodes have none.

Everything is seeded by `LocalFollowerConfig.seed`: the pool, the episode
draws and exploration (numpy Generator) and the range noise (the jitted
xorshift of `learn.jit`). Every hyperparameter is a field of
`LocalFollowerConfig`; `tools/local_follower_experiment.py` trains and
evaluates with the bench's own loop.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from firmware_py import robot_spec
from firmware_py.encoders import SectorEncoder
from firmware_py.localplan import LocalPlanner, LocalPlannerConfig, ObstacleMemory
from ground_station.learn.jit import seed_state
from ground_station.learn.sector.kernels import REVERSE, noisy_encode
from ground_station.learn.sector.obstacle_trainer import scenario_pool
from ground_station.learn.sector.obstacles import obs_period_step, sense_obs
from ground_station.learn.sector.reward import RW_COLLISION
from ground_station.learn.sector.twin import bearing_mrad, encode_fast, encoder_arrays
from ground_station.maps import GridMap, load_map
from ground_station.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS
from ground_station.nav.planned import FWD_MM_PER_PERIOD, PERIOD_US, grid_of
from ground_station.nav.scenario import Episode, rollout_arrays

TRAIN_MAPS = ("paper10", "rooms-16x16-s0", "trap-16x16-s0", "random-16x16-s0", "maze-16x16-s0")
BENCH_MAPS = ("paper10", "rooms-16x16-s1", "trap-16x16-s1", "random-16x16-s1", "maze-16x16-s1")


def follower_encoder() -> SectorEncoder:
    """The shipped sector policy's encoder (15 bearing sectors, sensors 0/1/7, edges 100/400 mm)."""
    return SectorEncoder(15, (0, 1, 7), (100, 400))


@dataclass
class LocalFollowerConfig:
    """Every hyperparameter of one training run."""

    seed: int = 0
    periods: int = 1_000_000  # control periods of training (episodes are cut at the end)
    maps: tuple[str, ...] = TRAIN_MAPS  # training maps (never the bench's -s1 maps)
    pool: int = 2000  # scenario episodes in the training pool
    k_max: int = 3  # static discs per episode, uniform in 0..k_max
    m_max: int = 2  # movers per episode, uniform in 0..m_max
    clear_share: float = 0.0  # share of episodes drawn from a second pool without obstacles (0: none)
    lr: float = 0.1  # learning rate at period 0 ...
    lr_end: float = 0.005  # ... linear to this at the last period
    gamma: float = 0.95  # discount per control period
    eps_start: float = 0.2  # exploration at period 0 (the start table already follows waypoints) ...
    eps_end: float = 0.05  # ... linear to this at eps_decay x periods, then held
    eps_decay: float = 0.5
    hold_max: int = 100  # periods an action is held while the state is unchanged (as the shipped trainer)
    noise_mm: float = 10.0  # std of Gaussian noise on the range readings the state sees (not the memory)
    progress: float = 1.0  # reward per cell of progress toward the period's target
    align: float = 1.0  # reward per pi rad the target's bearing turns toward straight ahead
    goal: float = 1.0  # bonus on reaching the last waypoint (episode ends)
    waypoint: float = 0.0  # bonus on reaching an intermediate waypoint
    collision: float = 1.0  # a contact's reward is -collision (episode ends)
    step_cost: float = 0.0  # cost per period
    reverse_cost: float = 0.02  # extra cost per reverse period
    reverse: int = 1  # 0: reverse is neither explored nor learnt, and never greedy in the result
    stall_free: int = 40  # periods without a new guide-potential minimum before stall_cost is charged
    stall_cost: float = 0.0  # cost per period beyond stall_free without progress
    stall_penalty: float = 0.0  # terminal reward -stall_penalty when the bench's loop rule ends the episode
    stall_steps: int = STALL_STEPS  # the bench's loop rule (periods without a new minimum)
    planner: dict[str, int] = field(default_factory=dict)  # LocalPlannerConfig overrides (default: the robot's)

    def planner_config(self) -> LocalPlannerConfig:
        return LocalPlannerConfig(**self.planner)

    def to_json(self) -> dict:
        d = asdict(self)
        d["maps"] = list(self.maps)
        return d


@dataclass
class TrainStats:
    """What a run did: episodes, their outcomes, and the periods spent."""

    episodes: int = 0
    successes: int = 0
    collisions: int = 0
    stalls: int = 0
    periods: int = 0
    reverse_periods: int = 0
    returns: list[float] = field(default_factory=list)

    def summary(self) -> dict:
        n = max(1, self.episodes)
        return {"episodes": self.episodes, "success_rate": self.successes / n, "collision_rate": self.collisions / n,
                "stall_rate": self.stalls / n, "periods": self.periods,
                "reverse_share": self.reverse_periods / max(1, self.periods),
                "mean_return": float(np.mean(self.returns)) if self.returns else 0.0}


class LocalFollowerTrainer:
    """Sequential Q-learning of a (405, 4) sector table in the planner loop (see the module docstring)."""

    def __init__(self, cfg: LocalFollowerConfig, maps: list[GridMap] | None = None) -> None:
        bench = set(BENCH_MAPS) - set(TRAIN_MAPS)
        if bench & set(cfg.maps):
            raise ValueError(f"training maps must not include the bench maps {sorted(bench & set(cfg.maps))}")
        self.cfg = cfg
        self.maps = maps if maps is not None else [load_map(n) for n in cfg.maps]
        self.by_name = {gm.name: gm for gm in self.maps}
        self.encoder = follower_encoder()
        self.sectors, self.sensors, self.edges, _ = encoder_arrays(self.encoder)
        self.which = np.ones(robot_spec.SENSOR_COUNT, dtype=np.bool_)
        self.pool: list[Episode] = scenario_pool(self.maps, cfg.pool, cfg.k_max, cfg.m_max, cfg.seed)
        n_clear = int(round(cfg.pool * cfg.clear_share / max(1e-9, 1.0 - cfg.clear_share))) if cfg.clear_share else 0
        self.clear_pool: list[Episode] = scenario_pool(self.maps, n_clear, 0, 0, cfg.seed + 1) if n_clear else []
        self.grids = {gm.name: grid_of(gm) for gm in self.maps}
        self.occs = {gm.name: np.ascontiguousarray(gm.occ, dtype=np.uint8) for gm in self.maps}
        self.rng = np.random.default_rng(cfg.seed)
        self.jrng = seed_state(cfg.seed)
        self.lp = cfg.planner_config()
        self.rw = np.zeros(7)
        self.rw[RW_COLLISION] = 1.0  # the kernel's own reward is not used (ours is toward the planner's target)
        self.t = 0  # global period count (schedules)
        self.stats = TrainStats()
        self.n_act = 4 if cfg.reverse else REVERSE  # reverse is the last action
        self._ranges = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
        self._status = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
        self._noisy = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
        self._nstatus = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)

    # schedules (linear in the global period, as the shipped trainer's)
    def epsilon(self) -> float:
        c = self.cfg
        n = c.eps_decay * c.periods
        frac = min(1.0, self.t / n) if n > 0 else 1.0
        return c.eps_start + (c.eps_end - c.eps_start) * frac

    def lr(self) -> float:
        c = self.cfg
        frac = min(1.0, self.t / c.periods) if c.periods > 0 else 1.0
        return c.lr + (c.lr_end - c.lr) * frac

    def state(self, x: float, y: float, th: float, tx: float, ty: float) -> int:
        b = bearing_mrad(x, y, th, tx, ty)
        if self.cfg.noise_mm > 0.0:
            return int(noisy_encode(self.jrng, self.cfg.noise_mm, b, self._ranges, self._status, self._noisy,
                                    self._nstatus, self.sectors, self.sensors, self.edges))
        return int(encode_fast(b, self._ranges, self._status, self.sectors, self.sensors, self.edges))

    def update(self, q: np.ndarray, s0: int, a: int, s2: int, racc: float, g: float, terminal: bool) -> None:
        target = racc if terminal else racc + g * float(q[s2, :self.n_act].max())
        q[s0, a] += self.lr() * (target - q[s0, a])

    def episode(self, q: np.ndarray, ep: Episode, max_periods: int) -> tuple[str, float, int]:
        """One epsilon-greedy training episode on ep, updating q; returns (outcome, return, periods)."""
        cfg = self.cfg
        gm = self.by_name[ep.map]
        occ = self.occs[ep.map]
        grid = self.grids[ep.map]
        h, w = occ.shape
        c = gm.cell_size_m * 1000.0
        discs, movers, wps, rem, plan_len = rollout_arrays(ep)
        x, y, th = ep.start
        budget = min(max_periods, int(BUDGET_BASE + BUDGET_FACTOR * plan_len / FWD_MM_PER_PERIOD))
        phi = math.hypot(x - wps[0, 0], y - wps[0, 1]) + rem[0]
        memory = ObstacleMemory(self.lp)
        planner = LocalPlanner(grid, self.lp)
        ranges, status = self._ranges, self._status
        sense_obs(occ, h, w, c, x, y, th, self.which, ranges, status, discs, movers)
        k, best, since, t = 0, phi, 0, 0
        memory.observe(grid, round(x), round(y), round(th * 1000.0), ranges.tolist(), status.tolist(), 0)
        tx, ty = planner.target(x, y, (round(wps[k, 0]), round(wps[k, 1])), memory)
        s = self.state(x, y, th, tx, ty)
        hold, a, s0, racc, g, ret = 0, 0, s, 0.0, 1.0, 0.0
        outcome = "timeout"
        while True:
            if hold == 0:
                explore = self.rng.random() < self.epsilon()
                a = int(self.rng.integers(self.n_act)) if explore else int(np.argmax(q[s, :self.n_act]))
                s0, racc, g = s, 0.0, 1.0
            d0 = math.hypot(x - tx, y - ty)
            b0 = abs(bearing_mrad(x, y, th, tx, ty))
            k0 = k
            x, y, th, phi, _, _, hit, success, _, k = obs_period_step(
                occ, h, w, c, x, y, th, phi, wps, rem, len(wps), k, a, self.rw, self.which, ranges, status,
                self.sectors, self.sensors, self.edges, discs, movers, 0.0)
            t += 1
            self.t += 1
            hold += 1
            s2 = -1
            terminal = False
            if a == REVERSE:
                self.stats.reverse_periods += 1
            if hit:
                r = -cfg.collision
                terminal, outcome = True, "collision"
            else:
                r = cfg.progress * (d0 - math.hypot(x - tx, y - ty)) / c - cfg.step_cost
                if cfg.align != 0.0:
                    r += cfg.align * (b0 - abs(bearing_mrad(x, y, th, tx, ty))) / math.pi / 1000.0
                if a == REVERSE:
                    r -= cfg.reverse_cost
                if success:
                    r += cfg.goal
                    terminal, outcome = True, "success"
                else:
                    if k != k0:
                        r += cfg.waypoint
                        planner.reset()
                    if phi < best - 1.0:
                        best, since = phi, 0
                    else:
                        since += 1
                        if since > cfg.stall_free:
                            r -= cfg.stall_cost
                        if since >= cfg.stall_steps:
                            outcome = "stall"
                            if cfg.stall_penalty > 0.0:
                                r -= cfg.stall_penalty
                                terminal = True
                    if not terminal:
                        memory.observe(grid, round(x), round(y), round(th * 1000.0), ranges.tolist(), status.tolist(),
                                       t * PERIOD_US)
                        tx, ty = planner.target(x, y, (round(wps[k, 0]), round(wps[k, 1])), memory)
                        s2 = self.state(x, y, th, tx, ty)
            racc += g * r
            ret += r
            g *= cfg.gamma
            end = terminal or outcome == "stall" or t >= budget or self.t >= cfg.periods
            if end or s2 != s0 or hold >= cfg.hold_max:
                self.update(q, s0, a, s2, racc, g, terminal)
                hold = 0
            if end:
                return outcome, ret, t
            s = s2

    def run(self, q: np.ndarray, progress: bool = True) -> TrainStats:
        """Train q (float64 (405, 4), updated in place) for cfg.periods periods."""
        if q.shape != (self.encoder.n_states, self.encoder.n_actions) or q.dtype != np.float64:
            raise ValueError(f"q must be float64 {(self.encoder.n_states, self.encoder.n_actions)}, "
                             f"got {q.dtype} {q.shape}")
        from tqdm import tqdm

        self.stats = TrainStats()
        st = self.stats
        with tqdm(total=self.cfg.periods, unit="period", unit_scale=True, disable=not progress,
                  desc="local follower", leave=False) as bar:
            while self.t < self.cfg.periods:
                if self.clear_pool and self.rng.random() < self.cfg.clear_share:
                    ep = self.clear_pool[int(self.rng.integers(len(self.clear_pool)))]
                else:
                    ep = self.pool[int(self.rng.integers(len(self.pool)))]
                t0 = self.t
                outcome, ret, n = self.episode(q, ep, self.cfg.periods - self.t)
                st.episodes += 1
                st.periods += n
                st.successes += outcome == "success"
                st.collisions += outcome == "collision"
                st.stalls += outcome == "stall"
                st.returns.append(ret)
                bar.update(self.t - t0)
                if st.episodes % 50 == 0:
                    bar.set_postfix(succ=f"{st.successes / st.episodes:.3f}", col=f"{st.collisions / st.episodes:.3f}")
        if not self.cfg.reverse:  # ties break to the lowest index: reverse is never greedy
            np.minimum(q[:, REVERSE], q[:, :REVERSE].max(axis=1), out=q[:, REVERSE])
        return st

__all__ = ["BENCH_MAPS", "TRAIN_MAPS", "LocalFollowerConfig", "LocalFollowerTrainer", "TrainStats",
           "follower_encoder"]
