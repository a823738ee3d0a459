"""Sector-encoding Q-learning and evaluation on the kinematic twin.

* `SectorTrainer(maps, cfg, encoder)`: exact sequential Q-learning (numba
  kernel in `ground_station.sector_kernels`), epsilon-greedy with a linear
  schedule on the global step, a random map, goal cell, start pose (inside a
  random free cell) and heading each episode, dense shaped reward.
  `run(q, start_step, n_steps)` advances n_steps env steps and returns the
  returns and successes of the episodes that finished; chunked runs equal
  one long run (the RNG and the open episode live in the trainer).
* `evaluate_sector(q, gridmap, encoder, ...)`: greedy rollouts from every
  (start cell centre, goal cell, heading) of a map, or a seeded sample of
  them; success, path length / octile shortest, collisions, loops, timeouts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware_py.encoders import SectorEncoder
from ground_station.maps import GridMap, octile_distances
from ground_station.sector_kernels import (
    COLLISION,
    EP_LEN,
    LOOP,
    SUCCESS,
    TIMEOUT,
    eval_kernel,
    seed_rng,
    train_kernel,
)
from ground_station.sector_twin import encoder_arrays, grid_of

MAX_TRAIN_CELLS = 64 * 64
DEFAULT_HOLD_MAX = 100  # periods an action is held while the state is unchanged (see sector_kernels)  # all-pairs distance tables are kept per training map


@dataclass(frozen=True)
class SectorReward:
    """Shaped reward of one control period (see `sector_kernels`)."""

    progress: float = 1.0   # per cell of progress along the octile potential
    step_cost: float = 0.01  # per control period
    reverse_cost: float = 0.02  # extra per reverse period (the robot has no rear bumper view)
    goal: float = 1.0
    collision: float = 1.0

    def array(self) -> np.ndarray:
        return np.array([self.progress, self.step_cost, self.reverse_cost, self.goal, self.collision])


@dataclass
class PackedMaps:
    """Training maps in the padded arrays the kernel takes."""

    occ: np.ndarray
    dims: np.ndarray
    cell: np.ndarray
    free: np.ndarray
    nfree: np.ndarray
    dist: np.ndarray


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


def _cfg(cfg, name: str, default):
    return getattr(cfg, name, default)


def epsilon_schedule(cfg) -> tuple[float, float, int]:
    """(start, end, decay steps) of the linear epsilon schedule from a TrainConfig
    (epsilon_start, epsilon_end, epsilon_decay = fraction of steps)."""
    start = float(_cfg(cfg, "epsilon_start", 1.0))
    end = float(_cfg(cfg, "epsilon_end", 0.05))
    frac = float(_cfg(cfg, "epsilon_decay", 0.5))
    return start, end, int(round(frac * int(cfg.steps)))


class SectorTrainer:
    """Exact sequential Q-learning of a SectorEncoder policy on the twin."""

    def __init__(self, maps: list[GridMap], cfg, encoder: SectorEncoder,
                 reward: SectorReward | None = None) -> None:
        self.maps = list(maps)
        self.cfg = cfg
        self.encoder = encoder
        # TrainConfig's reward_goal / reward_step / reward_collision (signed as
        # rewards) plus the sector-only progress and reverse terms
        self.reward = reward or SectorReward(
            progress=float(_cfg(cfg, "sector_progress_reward", SectorReward.progress)),
            step_cost=-float(_cfg(cfg, "reward_step", -SectorReward.step_cost)),
            reverse_cost=float(_cfg(cfg, "sector_reverse_cost", SectorReward.reverse_cost)),
            goal=float(_cfg(cfg, "reward_goal", SectorReward.goal)),
            collision=-float(_cfg(cfg, "reward_collision", -SectorReward.collision)),
        )
        self.packed = pack_maps(self.maps)
        self.n_states = encoder.n_states
        self.n_actions = encoder.n_actions
        self._enc = encoder_arrays(encoder)
        self._rng = seed_rng(int(cfg.seed))
        self._ep = np.zeros(EP_LEN)
        self._eps = epsilon_schedule(cfg)
        self._rw = self.reward.array()
        # 0 = automatic: 1000 periods (50 s) on paper10, scaled with the map area
        mes = int(_cfg(cfg, "max_episode_steps", 0))
        self.max_episode_steps = mes if mes > 0 else 10 * max(gm.occ.size for gm in self.maps)
        self.hold_max = int(_cfg(cfg, "sector_hold_max", DEFAULT_HOLD_MAX))

    def run(self, q: np.ndarray, start_step: int, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
        """Advance n_steps env steps, updating q (float64 (n_states, n_actions))
        in place; returns (returns, successes) of the episodes that finished."""
        if q.shape != (self.n_states, self.n_actions) or q.dtype != np.float64:
            raise ValueError(f"q must be float64 {(self.n_states, self.n_actions)}, got {q.dtype} {q.shape}")
        p = self.packed
        sectors, sensors, edges, which = self._enc
        out_ret = np.empty(n_steps)
        out_succ = np.empty(n_steps, dtype=np.bool_)
        n = train_kernel(q, self._rng, self._ep, p.occ, p.dims, p.cell, p.free, p.nfree, p.dist,
                         sectors, sensors, edges, which,
                         float(self.cfg.lr), float(self.cfg.gamma), *self._eps, self._rw,
                         self.max_episode_steps, self.hold_max, int(start_step), int(n_steps), out_ret, out_succ)
        return out_ret[:n].copy(), out_succ[:n].copy()


def eval_episodes(gridmap: GridMap, seed: int = 0, sample: int | None = None,
                  headings: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(starts, goals, heading indices) of the evaluation set: every ordered
    pair of distinct connected free cells x `headings` headings, or a seeded
    sample of `sample` of them."""
    cells = np.array(gridmap.free_cells(), dtype=np.int64)
    n = len(cells)
    si, gi = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    si, gi = si.ravel(), gi.ravel()
    keep = si != gi
    si, gi = si[keep], gi[keep]
    # connected pairs only: label components by octile reachability from each goal's field
    label = _components(gridmap, cells)
    keep = label[si] == label[gi]
    si, gi = si[keep], gi[keep]
    hh = np.tile(np.arange(headings), len(si))
    si = np.repeat(si, headings)
    gi = np.repeat(gi, headings)
    if sample is not None and sample < len(si):
        pick = np.sort(np.random.default_rng(seed).choice(len(si), size=sample, replace=False))
        si, gi, hh = si[pick], gi[pick], hh[pick]
    return cells[si], cells[gi], hh


def _components(gridmap: GridMap, cells: np.ndarray) -> np.ndarray:
    label = np.full(len(cells), -1, dtype=np.int64)
    index = {(int(c), int(r)): k for k, (c, r) in enumerate(cells)}
    nxt = 0
    for k in range(len(cells)):
        if label[k] >= 0:
            continue
        d = octile_distances(gridmap.occ, int(cells[k, 0]), int(cells[k, 1]))
        for (c, r), j in index.items():
            if np.isfinite(d[r, c]):
                label[j] = nxt
        nxt += 1
    return label


def evaluate_sector(q: np.ndarray, gridmap: GridMap, encoder: SectorEncoder, seed: int = 0,
                    sample: int | None = None, max_steps: int | None = None, headings: int = 8,
                    stall_steps: int = 400) -> dict:
    """Greedy rollouts of q over (start, goal, heading) on gridmap.

    Starts at cell centres with headings k*2pi/headings; goals at cell
    centres (reached within robot.GOAL_TOLERANCE_MM). Step budget per episode:
    max_steps if given, else 400 + 4 x the octile shortest path in forward
    control periods. Path ratio = driven length / octile shortest length
    between the cell centres, over successful episodes. A loop is an episode
    whose progress potential found no new minimum for `stall_steps` periods."""
    if q.shape != (encoder.n_states, encoder.n_actions):
        raise ValueError(f"q shape {q.shape} does not match the encoder's "
                         f"({encoder.n_states}, {encoder.n_actions})")
    starts, goals, hidx = eval_episodes(gridmap, seed=seed, sample=sample, headings=headings)
    n = len(starts)
    occ, h, w, c = grid_of(gridmap)
    ugoals, slot = np.unique(goals, axis=0, return_inverse=True)
    slot = slot.reshape(-1).astype(np.int64)
    dists = np.stack([octile_distances(gridmap.occ, int(gc), int(gr)) for gc, gr in ugoals]) \
        if n else np.zeros((0, h, w))
    sectors, sensors, edges, which = encoder_arrays(encoder)
    outcome = np.zeros(n, dtype=np.int64)
    path = np.zeros(n)
    steps = np.zeros(n, dtype=np.int64)
    th = hidx.astype(np.float64) * (2.0 * math.pi / headings)
    th = (th + math.pi) % (2.0 * math.pi) - math.pi
    eval_kernel(np.ascontiguousarray(q, dtype=np.float64), occ, h, w, c, dists, starts, goals, slot,
                th, sectors, sensors, edges, which, int(max_steps or 0), 400.0, 4.0,
                int(stall_steps), outcome, path, steps)
    shortest = dists[slot, starts[:, 1], starts[:, 0]] * c
    ok = outcome == SUCCESS
    ratios = path[ok] / shortest[ok]
    return {
        "map": gridmap.name,
        "episodes": int(n),
        "success_rate": float(ok.mean()) if n else 0.0,
        "path_ratio_mean": float(ratios.mean()) if ratios.size else float("nan"),
        "path_ratio_max": float(ratios.max()) if ratios.size else float("nan"),
        "path_ratio_median": float(np.median(ratios)) if ratios.size else float("nan"),
        "timeouts": int((outcome == TIMEOUT).sum()),
        "collisions": int((outcome == COLLISION).sum()),
        "loops": int((outcome == LOOP).sum()),
        "mean_steps": float(steps.mean()) if n else 0.0,
        "headings": int(headings),
        "sample": sample,
        "seed": int(seed),
    }
