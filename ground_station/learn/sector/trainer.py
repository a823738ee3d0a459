"""Sector-encoding Q-learning on the kinematic twin; read it top to bottom.

1. `pack_maps`: the training maps as the kernel takes them, with the octile
   distance field to every free cell.
2. `epsilon_schedule` (and the package's `sector_encoder`): what a TrainConfig asks for.
3. `SectorTrainer(maps, cfg, encoder)`: exact sequential Q-learning (the
   kernels' `train_kernel`) with a random map, goal cell, start pose and
   heading each episode; chunked runs equal one long run.
4. `train_sector` drives it in chunks; greedy evaluation is `sector.evaluate`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware_py.kinds.sector.encoder import SectorEncoder
from ground_station.learn.config import LEARNERS, TrainConfig
from ground_station.learn.jit import seed_state
from ground_station.learn.robot import training_profile
from ground_station.learn.sector import sector_encoder
from ground_station.learn.sector.kernels import (
    EP_LEN,
    L_DOUBLE_Q,
    train_kernel,
)
from ground_station.learn.sector.reward import SectorReward, check_guidance
from ground_station.learn.sector.twin import TwinRobot, bordered, encoder_arrays, grid_of
from ground_station.learn.train import TrainResult, run_trainer
from ground_station.maps import GridMap, octile_distances
from ground_station.maps.planner import clearance_mm

MAX_TRAIN_CELLS = 64 * 64  # all-pairs distance tables are kept per training map


@dataclass
class PackedMaps:
    """Training maps in the padded arrays the kernel takes."""

    occ: np.ndarray
    dims: np.ndarray
    cell: np.ndarray
    free: np.ndarray
    nfree: np.ndarray
    dist: np.ndarray

    def bordered(self) -> np.ndarray:
        """Each map in a one-cell obstacle frame (`twin.bordered`), stacked (M, Hmax + 2, Wmax + 2)."""
        m, hmax, wmax = self.occ.shape
        out = np.ones((m, hmax + 2, wmax + 2), dtype=np.uint8)
        for i in range(m):
            h, w = int(self.dims[i, 0]), int(self.dims[i, 1])
            out[i, :h + 2, :w + 2] = bordered(self.occ[i], h, w)
        return out


def pack_maps(maps: list[GridMap]) -> PackedMaps:
    """Pad and stack maps; precompute octile fields to every free cell."""
    if not maps:
        raise ValueError("at least one training map is needed")
    for gm in maps:
        if gm.occ.size > MAX_TRAIN_CELLS:
            raise ValueError(f"training map {gm.name} has {gm.occ.size} cells; the sector trainer "
                             f"keeps all-pairs distances and takes at most {MAX_TRAIN_CELLS}")
        if len(gm.free_cells()) < 2:
            raise ValueError(f"training map {gm.name} needs at least two free cells")
    hmax = max(gm.height for gm in maps)
    wmax = max(gm.width for gm in maps)
    fmax = max(len(gm.free_cells()) for gm in maps)
    m = len(maps)
    occ = np.ones((m, hmax, wmax), dtype=np.uint8)
    dims = np.zeros((m, 2), dtype=np.int64)
    cell = np.zeros(m)
    free = np.zeros((m, fmax, 2), dtype=np.int64)
    nfree = np.zeros(m, dtype=np.int64)
    dist = np.full((m, fmax, hmax, wmax), np.inf, dtype=np.float32)
    for i, gm in enumerate(maps):
        o, h, w, c = grid_of(gm)
        occ[i, :h, :w] = o
        dims[i] = (h, w)
        cell[i] = c
        cells = gm.free_cells()
        nfree[i] = len(cells)
        for k, (col, row) in enumerate(cells):
            free[i, k] = (col, row)
            dist[i, k, :h, :w] = octile_distances(gm.occ, col, row)
    return PackedMaps(occ, dims, cell, free, nfree, dist)


def epsilon_schedule(cfg: TrainConfig) -> tuple[float, float, int]:
    """(start, end, decay steps) of the linear epsilon schedule (epsilon_decay: a fraction of `steps`)."""
    return float(cfg.epsilon_start), float(cfg.epsilon_end), int(round(cfg.epsilon_decay * cfg.steps))


class SectorTrainer:
    """Exact sequential Q-learning of a SectorEncoder policy on the twin."""

    def __init__(self, maps: list[GridMap], cfg: TrainConfig, encoder: SectorEncoder,
                 reward: SectorReward | None = None, robot: TwinRobot | None = None) -> None:
        self.maps = list(maps)
        # the robot the twin plays: the config's profile (--profile), else the built-in robot
        self.robot = robot if robot is not None else TwinRobot.of_profile(training_profile(cfg))
        self._tw = self.robot.arrays()
        self.cfg = cfg
        self.encoder = encoder
        self.reward = reward or SectorReward.from_config(cfg)
        self.packed = pack_maps(self.maps)
        self.n_states = encoder.n_states
        self.n_actions = encoder.n_actions
        self._enc = encoder_arrays(encoder)
        self._rng = seed_state(int(cfg.seed))
        self._ep = np.zeros(EP_LEN)
        self._eps = epsilon_schedule(cfg)
        self._rw = self.reward.array()
        # 0 = automatic: 1000 periods (50 s) on paper10, scaled with the map area
        mes = int(cfg.max_episode_steps)
        self.max_episode_steps = mes if mes > 0 else 10 * max(gm.occ.size for gm in self.maps)
        self.hold_max = int(cfg.options.hold_max)
        self.lr_end = float(cfg.options.lr_end)
        self.noise_mm = float(cfg.options.range_noise_mm)
        self.guidance = str(cfg.options.guidance)
        self._guided = check_guidance(self.guidance)
        self._clear_r = clearance_mm(float(cfg.options.margin_mm), self.robot.radius_mm)
        self._max_seg = float(cfg.options.max_segment_mm)
        cells = int(self.packed.occ.shape[1] * self.packed.occ.shape[2])
        self._path = np.zeros((cells, 2), dtype=np.int64)  # planner scratch
        self._wps = np.zeros((cells, 2))  # the open episode's waypoints (kept across chunks)
        self._rem = np.zeros(cells)
        self._occb = self.packed.bordered()
        self._learner_state(cfg)

    def _learner_state(self, cfg: TrainConfig) -> None:
        """The learner's tables besides q (Double Q's B, `LearnerMemory`)."""
        from ground_station.learn.cell.learners import LearnerMemory

        self.learner = str(cfg.learner)
        self.code = LEARNERS.index(self.learner)
        self._lam = float(cfg.learner_lambda)
        self._n_plan = int(cfg.dyna_planning)
        self.q2: np.ndarray | None = None  # Double Q's B, created on the first run (starts as q)
        self._mem = LearnerMemory.make(cfg, self.code, self.n_states, self.n_actions, self.max_episode_steps)

    def table(self, q: np.ndarray) -> np.ndarray:
        """The run's greedy table: q, or (A + B) / 2 for Double Q (q is A)."""
        if self.code == L_DOUBLE_Q and self.q2 is not None:
            return (q + self.q2) / 2.0
        return q

    def run(self, q: np.ndarray, start_step: int, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
        """Advance n_steps, updating q (float64) in place: (returns, successes) of finished episodes."""
        if q.shape != (self.n_states, self.n_actions) or q.dtype != np.float64:
            raise ValueError(f"q must be float64 {(self.n_states, self.n_actions)}, got {q.dtype} {q.shape}")
        p, m = self.packed, self._mem
        sectors, sensors, edges, which = self._enc
        out_ret = np.empty(n_steps)
        out_succ = np.empty(n_steps, dtype=np.bool_)
        if self.code == L_DOUBLE_Q:
            if self.q2 is None:
                self.q2 = q.copy()  # B starts where A starts (zeros or the same random init)
            q2 = self.q2
        else:
            q2 = q  # unused
        n = train_kernel(self.code, q, q2, self._rng, self._ep, p.occ, self._occb, p.dims, p.cell, p.free,
                         p.nfree, p.dist, sectors, sensors, edges, which,
                         float(self.cfg.lr), self.lr_end, int(self.cfg.steps), float(self.cfg.gamma),
                         *self._eps, self._rw, self.max_episode_steps, self.hold_max, self._guided,
                         self._clear_r, self._max_seg, self._path, self._wps, self._rem, self.noise_mm,
                         self._lam, self._n_plan, m.model_s2, m.model_r, m.model_g,
                         m.model_term, m.seen, m.n_seen, m.tr_s, m.tr_a, m.tr_e,
                         m.tr, int(start_step), int(n_steps), out_ret, out_succ, self._tw)
        return out_ret[:n].copy(), out_succ[:n].copy()


def train_sector(cfg: TrainConfig, gridmap: GridMap, progress: bool = False) -> TrainResult:
    """Train on the sector twin on `gridmap` plus the extra maps (--sector-maps)."""
    encoder = sector_encoder(cfg)
    trainer, q, rets, succs, seconds = run_trainer(lambda maps: SectorTrainer(maps, cfg, encoder), cfg, gridmap,
                                                   progress, "train sector")
    q, q2 = trainer.table(q), trainer.q2  # Double Q: (A + B) / 2 and B
    return TrainResult(q, rets, succs,
                       {"encoder": encoder.to_dict(), "guidance": trainer.guidance,
                        "margin_mm": cfg.options.margin_mm, "max_segment_mm": cfg.options.max_segment_mm,
                        "train_maps": [m.name for m in trainer.maps]}, seconds, q2)
