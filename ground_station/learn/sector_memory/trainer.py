"""Training and greedy evaluation of the cell-stepped `sector-memory` encoding
(`GridBugEncoder`) on the grid twin (`kernels`), direct setting: the goal vector
only, no waypoints, no map in the state.

* `hand_table(encoder)`: the hand-written table in the same state (go: the free
  goal-ward move, forward first; wall on the right: the right-hand rule, right,
  forward, left, back; on the left its mirror): the mode rules' baseline.
* `GridBugTrainer`: exact sequential Q-learning; chunked runs equal one long run.
* `evaluate_gridbug`: greedy rollouts over every (start cell, goal cell,
  heading) of a map (or a seeded sample), path ratio against the 4-connected
  BFS optimum, the share of moves in a wall mode.
"""

from __future__ import annotations

import math

import numpy as np

from firmware_py.kinds.sector_memory import gridbug as gb
from ground_station.learn.config import TrainConfig
from ground_station.learn.jit import seed_state
from ground_station.learn.sector.evaluate import eval_episodes
from ground_station.learn.sector_memory import encoder_of
from ground_station.learn.sector_memory.kernels import (
    COLLISION,
    SUCCESS,
    TIMEOUT,
    eval_kernel,
    train_kernel,
)
from ground_station.learn.train import TrainResult, run_trainer
from ground_station.maps import GridMap
from ground_station.maps.distances import bfs_distances

# (forward sign, left sign) of each sector (inverse of firmware_py.kinds.sector_memory.gridbug._SECTOR)
SECTOR_SIGNS = ((1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1))
WALL_ORDER = {1: (gb.MOVE_RIGHT, gb.MOVE_FORWARD, gb.MOVE_LEFT, gb.MOVE_BACK),  # wall on the right: right-hand rule
              2: (gb.MOVE_LEFT, gb.MOVE_FORWARD, gb.MOVE_RIGHT, gb.MOVE_BACK)}
GO_ORDER = (gb.MOVE_FORWARD, gb.MOVE_LEFT, gb.MOVE_RIGHT, gb.MOVE_BACK)


def gridbug_encoder(cfg: TrainConfig) -> gb.GridBugEncoder:
    return encoder_of(cfg.options)


def encoder_params(encoder: gb.GridBugEncoder) -> np.ndarray:
    """The kernels' `params`: cell_mm, leave_margin_mm, wall_bearing, wall_states."""
    return np.array([encoder.cell_mm, encoder.leave_margin_mm, int(encoder.wall_bearing), encoder.wall_states],
                    dtype=np.int64)


def _ranked(order: tuple[int, ...], free: int) -> np.ndarray:
    """Q row: the free moves in `order` get 4, 3, ...; blocked moves stay below every free one."""
    row = np.zeros(4)
    v = 8.0
    for k in order:
        if free >> k & 1:
            row[k] = v
            v -= 1.0
    for k in order:
        if not free >> k & 1:
            row[k] = -v
            v -= 1.0
    return row


def hand_table(encoder: gb.GridBugEncoder) -> np.ndarray:
    """The hand-written policy in the encoder's state (module docstring)."""
    q = np.zeros((encoder.n_states, encoder.n_actions))
    for sector, (sf, sl) in enumerate(SECTOR_SIGNS):
        goalward = [k for k, sgn in zip((gb.MOVE_FORWARD, gb.MOVE_LEFT, gb.MOVE_BACK, gb.MOVE_RIGHT),
                                        (sf, sl, -sf, -sl), strict=True)
                    if sgn == 1]
        order = tuple(k for k in GO_ORDER if k in goalward) + tuple(k for k in GO_ORDER if k not in goalward)
        for free in range(gb.N_FREE):
            q[sector * gb.N_FREE + free] = _ranked(order, free)
    base = gb.N_SECTORS * gb.N_FREE
    for mode in (1, 2):
        for w in range(encoder.wall_states):
            q[base + (mode - 1) * encoder.wall_states + w] = _ranked(WALL_ORDER[mode], w % gb.N_FREE)
    return q


class PackedMaps:
    """Training maps as the kernel takes them (padded to the largest)."""

    def __init__(self, maps: list[GridMap]) -> None:
        hmax = max(m.height for m in maps)
        wmax = max(m.width for m in maps)
        cells = [np.array(m.free_cells(), dtype=np.int64) for m in maps]
        fmax = max(len(c) for c in cells)
        self.occs = np.ones((len(maps), hmax, wmax), dtype=np.uint8)
        self.dims = np.zeros((len(maps), 2), dtype=np.int64)
        self.free = np.zeros((len(maps), fmax, 2), dtype=np.int64)
        self.nfree = np.zeros(len(maps), dtype=np.int64)
        self.bfs = np.full((len(maps), fmax, hmax, wmax), -1, dtype=np.int32)
        for i, (m, c) in enumerate(zip(maps, cells, strict=True)):
            self.occs[i, :m.height, :m.width] = m.occ
            self.dims[i] = (m.height, m.width)
            self.free[i, :len(c)] = c
            self.nfree[i] = len(c)
            for j, (gc, gr) in enumerate(c):
                self.bfs[i, j, :m.height, :m.width] = bfs_distances(m.occ, int(gc), int(gr))


class GridBugTrainer:
    """Exact sequential Q-learning of a gb.GridBugEncoder table on the grid twin."""

    def __init__(self, maps: list[GridMap], cfg: TrainConfig, encoder: gb.GridBugEncoder) -> None:
        self.cfg = cfg
        self.encoder = encoder
        self.n_states = encoder.n_states
        self.n_actions = encoder.n_actions
        self.maps = maps
        self.packed = PackedMaps(maps)
        self.params = encoder_params(encoder)
        self._rng = seed_state(cfg.seed)
        self._ep = np.zeros(7, dtype=np.int64)
        self._mem = np.zeros(4, dtype=np.int64)
        self._acc = np.zeros(1)
        self.max_episode_steps = int(cfg.max_episode_steps) or 10 * int(self.packed.nfree.max())
        self._eps = (float(cfg.epsilon_start), float(cfg.epsilon_end), int(cfg.epsilon_decay * cfg.steps))

    def run(self, q: np.ndarray, start_step: int, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
        if q.shape != (self.n_states, self.n_actions) or q.dtype != np.float64:
            raise ValueError(f"q must be float64 {(self.n_states, self.n_actions)}, got {q.dtype} {q.shape}")
        p = self.packed
        cfg = self.cfg
        out_ret = np.empty(n_steps)
        out_succ = np.empty(n_steps, dtype=np.bool_)
        n = train_kernel(q, self._rng, p.occs, p.dims, p.free, p.nfree, p.bfs, self.params,
                         float(cfg.lr), float(cfg.options.lr_end), int(cfg.steps), float(cfg.gamma), *self._eps,
                         float(cfg.reward_goal), float(cfg.reward_step), float(cfg.reward_collision),
                         float(cfg.options.wall_cost), float(cfg.options.go_reward), self.max_episode_steps,
                         self._ep, self._mem, self._acc, int(start_step), int(n_steps), out_ret, out_succ)
        return out_ret[:n].copy(), out_succ[:n].copy()


def train_sector_memory(cfg: TrainConfig, gridmap: GridMap, progress: bool = False) -> TrainResult:
    """Q-learning on the grid twin on `gridmap` plus the extra maps (--sector-maps)."""
    encoder = gridbug_encoder(cfg)
    trainer, q, rets, succs, seconds = run_trainer(lambda maps: GridBugTrainer(maps, cfg, encoder), cfg, gridmap,
                                                   progress, "train sector-memory")
    return TrainResult(q, rets, succs,
                       {"encoder": encoder.to_dict(), "guidance": "direct",
                        "train_maps": [m.name for m in trainer.maps]}, seconds)

def initial_dirs(hidx: np.ndarray, headings: int) -> np.ndarray:
    """Grid direction the robot turns to before its first decision, per heading index (as the robot:
    `firmware_py.kinds.sector_memory.gridbug.grid_dir_of` of the heading in mrad)."""
    return np.array([gb.grid_dir_of(int(round(k * 2000.0 * math.pi / headings))) for k in range(headings)],
                    dtype=np.int64)[hidx]


def evaluate_gridbug(q: np.ndarray, gridmap: GridMap, encoder: gb.GridBugEncoder, seed: int = 0,
                     sample: int | None = None, headings: int = 8, max_steps: int | None = None) -> dict:
    """Greedy rollouts of a table over every (start, goal, heading) of `gridmap` (or a seeded
    sample, as `eval_episodes`). A move into an obstacle is a collision and ends the episode;
    the budget is `max_steps` moves (default 10 x the free cells)."""
    if q.shape != (encoder.n_states, encoder.n_actions):
        raise ValueError(f"q shape {q.shape} does not match the encoder's ({encoder.n_states}, {encoder.n_actions})")
    starts, goals, hidx = eval_episodes(gridmap, seed=seed, sample=sample, headings=headings)
    n = len(starts)
    occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
    budget = int(max_steps or 10 * len(gridmap.free_cells()))
    outcome = np.zeros(n, dtype=np.int64)
    moves = np.zeros(n, dtype=np.int64)
    wall = np.zeros(n, dtype=np.int64)
    end_mode = np.zeros(n, dtype=np.int64)
    eval_kernel(np.ascontiguousarray(q, dtype=np.float64), occ, gridmap.height, gridmap.width,
                encoder_params(encoder), starts, goals, initial_dirs(hidx, headings), budget,
                outcome, moves, wall, end_mode)
    ok = outcome == SUCCESS
    shortest = np.zeros(n)
    for g in np.unique(goals, axis=0) if n else []:
        sel = (goals[:, 0] == g[0]) & (goals[:, 1] == g[1])
        d = bfs_distances(gridmap.occ, int(g[0]), int(g[1]))
        shortest[sel] = d[starts[sel, 1], starts[sel, 0]]
    ratios = moves[ok] / shortest[ok]
    fail = ~ok
    return {
        "map": gridmap.name, "episodes": int(n), "guidance": "direct", "encoding": "sector-memory",
        "success_rate": float(ok.mean()) if n else 0.0,
        "collisions": int((outcome == COLLISION).sum()),
        "timeouts": int((outcome == TIMEOUT).sum()),
        "timeouts_in_wall_mode": int((fail & (outcome == TIMEOUT) & (end_mode != gb.MODE_GO)).sum()),
        "path_ratio_mean": float(ratios.mean()) if ratios.size else float("nan"),
        "path_ratio_median": float(np.median(ratios)) if ratios.size else float("nan"),
        "path_ratio_max": float(ratios.max()) if ratios.size else float("nan"),
        "mean_moves": float(moves.mean()) if n else 0.0,
        "wall_share": float(wall.sum() / max(1, moves.sum())),
        "headings": int(headings), "sample": sample, "seed": int(seed), "max_moves": budget,
    }


def evaluate_policy(q: np.ndarray, run, gridmap: GridMap, *, sample: int | None = None,  # type: ignore[no-untyped-def]
                    seed: int = 0, full: bool = False) -> dict:
    """The kind's evaluation: `evaluate_gridbug` of a run's table; `full` adds the hand-written
    Bug rule on the same episodes as `baseline`."""
    rep = evaluate_gridbug(q, gridmap, run.encoder, seed=seed, sample=sample)
    if full:
        rep["baseline"] = evaluate_gridbug(hand_table(run.encoder), gridmap, run.encoder, seed=seed, sample=sample)
    return rep
