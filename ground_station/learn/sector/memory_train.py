"""Training and greedy evaluation of the `sector-memory` encoding (direct
setting: the goal's bearing and distance, no waypoints).

* `memory_encoder(cfg)`: the reference `MemorySectorEncoder` a TrainConfig
  asks for (the sector_* fields plus the memory_* fields).
* `MemoryTrainer`: `SectorTrainer` with the jitted Bug memory
  (`ground_station.learn.sector.memory.train_memory_kernel`); chunked runs
  equal one long run (the RNG, the open episode and its memory live here).
* `evaluate_memory(q, gridmap, encoder, ...)`: greedy rollouts over every
  (start cell centre, goal cell, heading) of a map or a seeded sample, the
  same episodes and figures as `evaluate_sector` in its direct setting, plus
  the share of periods spent following a wall and the failed episodes by
  class (`failure_classes`: collisions per mode, wall modes that never left,
  go-mode spins).
"""

from __future__ import annotations

import math

import numpy as np

from firmware_py.encoders import MemorySectorEncoder
from ground_station.learn.config import TrainConfig, int_list
from ground_station.learn.sector.evaluate import eval_episodes
from ground_station.learn.sector.kernels import COLLISION, LOOP, SUCCESS, TIMEOUT
from ground_station.learn.sector.memory import (
    F_CLOSER_BLOCKED,
    F_STUCK,
    MEM_LEN,
    MODE_GO,
    eval_memory_diag,
    train_memory_kernel,
)
from ground_station.learn.sector.trainer import SectorTrainer
from ground_station.learn.sector.twin import encoder_arrays, grid_of
from ground_station.maps import GridMap, octile_distances


def memory_encoder(cfg: TrainConfig) -> MemorySectorEncoder:
    """The reference MemorySectorEncoder of a config."""
    return MemorySectorEncoder(bearing_sectors=int(cfg.sector_bearing_sectors),
                               sensors=int_list(cfg.sector_sensors, "sector_sensors"),
                               range_edges_mm=int_list(cfg.sector_range_edges, "sector_range_edges"),
                               block_mm=int(cfg.memory_block_mm), block_bearing_mrad=int(cfg.memory_block_bearing_mrad),
                               leave_margin_mm=int(cfg.memory_leave_margin_mm))


def memory_params(encoder: MemorySectorEncoder, reach_mm: int = 400) -> np.ndarray:
    """The kernels' `mp` array: (block_mm, block_bearing_mrad,
    leave_margin_mm, bearing_sectors, range states, wall reach mm, mode states)."""
    return np.array([encoder.block_mm, encoder.block_bearing_mrad, encoder.leave_margin_mm,
                     encoder.bearing_sectors, encoder.range_states, reach_mm, encoder.mode_states], dtype=np.int64)


class MemoryTrainer(SectorTrainer):
    """Exact sequential Q-learning of a MemorySectorEncoder policy on the twin (direct)."""

    def __init__(self, maps: list[GridMap], cfg: TrainConfig, encoder: MemorySectorEncoder) -> None:
        super().__init__(maps, cfg, encoder.base)
        self.memory = encoder
        self.n_states = encoder.n_states
        self.guidance = "direct"
        self._mem = np.zeros(MEM_LEN, dtype=np.int64)
        self._mp = memory_params(encoder, int(cfg.memory_wall_reach_mm))
        self._wall_rw = float(cfg.memory_wall_reward)
        self._wall_away = float(cfg.memory_wall_away)
        self._go_euclid = int(cfg.memory_go_progress == "euclid")
        # the leaving rule reads the sensor nearest the goal, the wall reward the side sensors: sense all
        self._enc = (*self._enc[:3], np.ones_like(self._enc[3]))

    def run(self, q: np.ndarray, start_step: int, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
        if q.shape != (self.n_states, self.n_actions) or q.dtype != np.float64:
            raise ValueError(f"q must be float64 {(self.n_states, self.n_actions)}, got {q.dtype} {q.shape}")
        p = self.packed
        sectors, sensors, edges, which = self._enc
        out_ret = np.empty(n_steps)
        out_succ = np.empty(n_steps, dtype=np.bool_)
        n = train_memory_kernel(q, self._rng, self._ep, self._mem, p.occ, p.dims, p.cell, p.free, p.nfree, p.dist,
                                sectors, sensors, edges, which, self._mp, self.encoder.n_states, self._wall_rw, self._wall_away, self._go_euclid,
                                float(self.cfg.lr), self.lr_end, int(self.cfg.steps), float(self.cfg.gamma),
                                *self._eps, self._rw, self.max_episode_steps, self.hold_max,
                                self._path, self._wps, self._rem, self.noise_mm,
                                int(start_step), int(n_steps), out_ret, out_succ)
        return out_ret[:n].copy(), out_succ[:n].copy()


def failure_classes(outcome: np.ndarray, end_mode: np.ndarray, flags: np.ndarray) -> dict[str, int]:
    """Count the failed episodes by what went wrong (`eval_memory_diag`'s
    records): a collision in the go mode or in a wall mode; a timeout or
    loop ending in a wall mode after the goal had come `leave_margin_mm`
    closer than the hit while the goal-ward sensor kept the robot on the
    wall ("wall_leave_blocked"), or without that ("wall_circling": the
    wall followed never brought the goal that much closer); ending in the go
    mode with the centre (nearly) still over the last 200 periods
    ("go_stuck": spinning or dithering) or moving ("go_wandering")."""
    fail = outcome != SUCCESS
    coll = outcome == COLLISION
    go = end_mode == MODE_GO
    other = fail & ~coll
    return {
        "collision_go": int((coll & go).sum()),
        "collision_wall": int((coll & ~go).sum()),
        "wall_leave_blocked": int((other & ~go & ((flags & F_CLOSER_BLOCKED) != 0)).sum()),
        "wall_circling": int((other & ~go & ((flags & F_CLOSER_BLOCKED) == 0)).sum()),
        "go_stuck": int((other & go & ((flags & F_STUCK) != 0)).sum()),
        "go_wandering": int((other & go & ((flags & F_STUCK) == 0)).sum()),
    }


def evaluate_memory(q: np.ndarray, gridmap: GridMap, encoder: MemorySectorEncoder, seed: int = 0,
                    sample: int | None = None, max_steps: int | None = None, headings: int = 8,
                    stall_steps: int = 1000) -> dict:
    """Greedy rollouts of a sector-memory table, direct setting. Step budget
    and path ratio as `evaluate_sector`; `wall_share` = periods in a
    wall-following mode / all periods."""
    if q.shape != (encoder.n_states, encoder.n_actions):
        raise ValueError(f"q shape {q.shape} does not match the encoder's ({encoder.n_states}, {encoder.n_actions})")
    starts, goals, hidx = eval_episodes(gridmap, seed=seed, sample=sample, headings=headings)
    n = len(starts)
    occ, h, w, c = grid_of(gridmap)
    ugoals, slot = np.unique(goals, axis=0, return_inverse=True)
    slot = slot.reshape(-1).astype(np.int64)
    dists = np.stack([octile_distances(gridmap.occ, int(gc), int(gr)) for gc, gr in ugoals]) \
        if n else np.zeros((0, h, w))
    sectors, sensors, edges, which = encoder_arrays(encoder.base)
    which = np.ones_like(which)  # the leaving rule may read any sensor
    outcome = np.zeros(n, dtype=np.int64)
    path = np.zeros(n)
    steps = np.zeros(n, dtype=np.int64)
    wall = np.zeros(n, dtype=np.int64)
    th = hidx.astype(np.float64) * (2.0 * math.pi / headings)
    th = (th + math.pi) % (2.0 * math.pi) - math.pi
    end_mode = np.zeros(n, dtype=np.int64)
    flags = np.zeros(n, dtype=np.int64)
    eval_memory_diag(np.ascontiguousarray(q, dtype=np.float64), occ, h, w, c, dists, starts, goals, slot, th,
                     sectors, sensors, edges, which, memory_params(encoder), encoder.base.n_states,
                     int(max_steps or 0), 400.0, 4.0, int(stall_steps), outcome, path, steps, wall, end_mode, flags)
    shortest = dists[slot, starts[:, 1], starts[:, 0]] * c if n else np.zeros(0)
    ok = outcome == SUCCESS
    ratios = path[ok] / shortest[ok]
    return {
        "map": gridmap.name, "episodes": int(n), "guidance": "direct",
        "success_rate": float(ok.mean()) if n else 0.0,
        "path_ratio_mean": float(ratios.mean()) if ratios.size else float("nan"),
        "path_ratio_max": float(ratios.max()) if ratios.size else float("nan"),
        "path_ratio_median": float(np.median(ratios)) if ratios.size else float("nan"),
        "timeouts": int((outcome == TIMEOUT).sum()),
        "collisions": int((outcome == COLLISION).sum()),
        "loops": int((outcome == LOOP).sum()),
        "mean_steps": float(steps.mean()) if n else 0.0,
        "wall_share": float(wall.sum() / max(1, steps.sum())),
        "failures": failure_classes(outcome, end_mode, flags),
        "headings": int(headings), "sample": sample, "seed": int(seed),
    }
