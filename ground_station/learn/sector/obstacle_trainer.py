"""Sector Q-learning with unmapped obstacles: the trainer behind
`--sector-obstacles K --sector-movers M`.

Draws a seeded pool of `sector_pool` scenario episodes over the training
maps (`ground_station.nav.scenario.make_episode`: planner waypoints, up to
K detourable static discs and M movers, each count uniform in 0..K / 0..M
so open stretches without obstacles stay in the mix), then runs
`ground_station.learn.sector.obstacles.obs_train_kernel` on it: the same
epsilon-greedy, held-action, noisy-range Q-learning as `SectorTrainer`, the
same reward (`SectorReward`) plus `sector_clear_reward` per period closer
than `sector_clear_mm` to an unmapped obstacle. Same interface as
`SectorTrainer` (`run(q, start_step, n_steps) -> (returns, successes)`), so
`ground_station.learn.train.train_sector` drives either; seeded throughout.

With a `MemorySectorEncoder` (the detour memory: Bug-style mode + side
held per waypoint + previous turn, the robot's reference encoder, reset per
mission item by the controller) the kernel is `obs_mem_train_kernel`: the
same loop with the memory carried in the episode; `frozen` (bool per
state, set by the caller) keeps chosen rows as they are, e.g. go rows
copied from the shipped sector table while the wall rows learn.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from firmware_py.encoders import MemorySectorEncoder, SectorEncoder
from ground_station.learn.config import TrainConfig
from ground_station.learn.jit import seed_state
from ground_station.learn.sector.memory_train import memory_params
from ground_station.learn.sector.obstacles import obs_mem_train_kernel, obs_train_kernel
from ground_station.learn.sector.reward import SectorReward
from ground_station.learn.sector.trainer import epsilon_schedule
from ground_station.learn.sector.twin import RADIUS_MM, encoder_arrays
from ground_station.maps import GridMap, MapError
from ground_station.nav.scenario import Episode, episode_arrays, make_episode


def scenario_pool(maps: list[GridMap], n: int, k_max: int, m_max: int, seed: int,
                  plan_kw: dict | None = None) -> list[Episode]:
    """n seeded training episodes: a random map, connected start/goal cells,
    heading, and uniform 0..k_max discs / 0..m_max movers."""
    rng = np.random.default_rng(seed)
    cells = [gm.free_cells() for gm in maps]
    out: list[Episode] = []
    while len(out) < n:
        mi = int(rng.integers(len(maps)))
        a, b = rng.choice(len(cells[mi]), size=2, replace=False)
        s, g = cells[mi][int(a)], cells[mi][int(b)]
        k = int(rng.integers(k_max + 1))
        m = int(rng.integers(m_max + 1))
        try:
            ep = make_episode(maps[mi], s, g, float(rng.uniform(-math.pi, math.pi)), k, m,
                              seed=int(rng.integers(2**31)), plan_kw=plan_kw)
        except MapError:
            continue
        out.append(ep)
    return out


class ObstacleSectorTrainer:
    """Exact sequential Q-learning of a SectorEncoder policy on a scenario pool."""

    def __init__(self, maps: list[GridMap], cfg: TrainConfig, encoder: SectorEncoder | MemorySectorEncoder,
                 reward: SectorReward | None = None) -> None:
        if cfg.sector_guidance != "path":
            raise ValueError("training with obstacles follows the planner's waypoints: sector_guidance must be path")
        self.maps = list(maps)
        self.cfg = cfg
        self.encoder = encoder
        self.reward = reward or SectorReward.from_config(cfg)
        self.n_states = encoder.n_states
        self.n_actions = encoder.n_actions
        self.guidance = "path"
        plan_kw = {"margin_mm": float(cfg.sector_margin_mm), "max_segment_mm": float(cfg.sector_max_segment_mm)}
        self.pool = scenario_pool(self.maps, int(cfg.sector_pool), int(cfg.sector_obstacles),
                                  int(cfg.sector_movers), int(cfg.seed), plan_kw)
        self.arrays = episode_arrays(self.pool, {gm.name: gm for gm in self.maps})
        self.frozen = np.zeros(0, dtype=np.bool_)  # memory encoders: rows (states) Q-learning leaves alone
        self.stall_steps = 0  # memory encoders: > 0 ends a stalled episode as a failure (the bench's loop rule)
        self.stall_cost = 0.0
        if isinstance(encoder, MemorySectorEncoder):
            self._mp = memory_params(encoder)
            self._n_base = encoder.base.n_states
            sectors, sensors, edges, which = encoder_arrays(encoder.base)
            self._enc = (sectors, sensors, edges, np.ones_like(which))  # the memory reads every sensor
        else:
            self._mp = np.zeros(0, dtype=np.int64)
            self._n_base = encoder.n_states
            self._enc = encoder_arrays(encoder)
        self._rng = seed_state(int(cfg.seed))
        self._eps = epsilon_schedule(cfg)
        rw = np.zeros(7)
        rw[:6] = self.reward.array()
        rw[6] = float(cfg.sector_clear_reward)
        self._rw = rw
        mes = int(cfg.max_episode_steps)
        self.max_episode_steps = mes if mes > 0 else 10 * max(gm.occ.size for gm in self.maps)
        cell = min(gm.cell_size_m for gm in self.maps) * 1000.0
        self._jitter = max(0.0, 0.5 * cell - RADIUS_MM - 1.0)

    def run(self, q: np.ndarray, start_step: int, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
        """Advance n_steps env steps, updating q (float64) in place; returns
        (returns, successes) of the episodes that finished."""
        if q.shape != (self.n_states, self.n_actions) or q.dtype != np.float64:
            raise ValueError(f"q must be float64 {(self.n_states, self.n_actions)}, got {q.dtype} {q.shape}")
        a = self.arrays
        sectors, sensors, edges, which = self._enc
        cfg = self.cfg
        out_ret = np.empty(n_steps)
        out_succ = np.empty(n_steps, dtype=np.bool_)
        common = (sectors, sensors, edges, which)
        tail = (float(cfg.lr), float(cfg.sector_lr_end), float(cfg.gamma), *self._eps, self._rw,
                float(cfg.sector_clear_mm), self.max_episode_steps, int(cfg.sector_hold_max),
                float(cfg.sector_range_noise_mm), self._jitter, int(start_step), int(cfg.steps), int(n_steps),
                out_ret, out_succ)
        head = (q, self._rng, a["occ"], a["dims"], a["cells"], a["map"], a["start"], a["wp"], a["nwp"], a["rem"],
                a["discs"], a["nd"], a["movers"], a["nm"])
        if self._mp.shape[0]:
            n = obs_mem_train_kernel(*head, *common, self._mp, self._n_base, self.frozen,
                                     self.stall_steps, self.stall_cost, *tail)
        else:
            n = obs_train_kernel(*head, *common, *tail)
        return out_ret[:n].copy(), out_succ[:n].copy()

    def train(self, q: np.ndarray, steps: int, chunk: int = 2_000_000,
              report: Callable[[str], None] | None = print) -> None:
        """`run` for `steps` steps from step 0 in chunks, reporting the training success after each
        (the experiment tools' loop)."""
        t0 = time.perf_counter()
        done = 0
        while done < steps:
            n = min(chunk, steps - done)
            _, succ = self.run(q, done, n)
            done += n
            if report is not None:
                report(f"{done} steps, training success {succ.mean() if len(succ) else 0:.3f}, "
                       f"{time.perf_counter() - t0:.0f} s")
