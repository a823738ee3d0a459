"""Sector-encoding Q-learning and evaluation on the kinematic twin.

* `SectorTrainer(maps, cfg, encoder)`: exact sequential Q-learning (numba
  kernel in `ground_station.learn.sector.kernels`), epsilon-greedy with a linear
  schedule on the global step, a random map, goal cell, start pose (inside a
  random free cell) and heading each episode, dense shaped reward.
  `run(q, start_step, n_steps)` advances n_steps env steps and returns the
  returns and successes of the episodes that finished; chunked runs equal
  one long run (the RNG and the open episode live in the trainer).
* `evaluate_sector(q, gridmap, encoder, ..., guidance="path"|"direct")`:
  greedy rollouts from every (start cell centre, goal cell, heading) of a
  map, or a seeded sample of them; success, path length / octile shortest,
  collisions, loops, timeouts. Guidance "path" follows the ground station's
  planned waypoints (`ground_station.maps.planner`, what the robot gets as a
  mission); "direct" steers on the goal's bearing alone (pure reactive).
  `direct=True` adds the direct figures beside the guided ones, and
  `baseline=True` a hand-written seek table judged the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware_py.encoders import SectorEncoder
from ground_station.learn.config import TrainConfig
from ground_station.learn.jit import seed_state
from ground_station.learn.sector.kernels import (
    COLLISION,
    EP_LEN,
    LOOP,
    SUCCESS,
    TIMEOUT,
    eval_kernel,
    train_kernel,
)
from ground_station.learn.sector.reward import SectorReward, check_guidance
from ground_station.learn.sector.twin import encoder_arrays, grid_of
from ground_station.maps import GridMap, octile_distances
from ground_station.maps.planner import (
    DEFAULT_MARGIN_MM,
    DEFAULT_MAX_SEGMENT_MM,
    clearance_mm,
    plan_into,
)

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
    """(start, end, decay steps) of the linear epsilon schedule
    (epsilon_decay is a fraction of `steps`)."""
    return float(cfg.epsilon_start), float(cfg.epsilon_end), int(round(cfg.epsilon_decay * cfg.steps))


class SectorTrainer:
    """Exact sequential Q-learning of a SectorEncoder policy on the twin."""

    def __init__(self, maps: list[GridMap], cfg: TrainConfig, encoder: SectorEncoder,
                 reward: SectorReward | None = None) -> None:
        self.maps = list(maps)
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
        self.hold_max = int(cfg.sector_hold_max)
        self.lr_end = float(cfg.sector_lr_end)
        self.noise_mm = float(cfg.sector_range_noise_mm)
        self.guidance = str(cfg.sector_guidance)
        self._guided = check_guidance(self.guidance)
        self._clear_r = clearance_mm(float(cfg.sector_margin_mm))
        self._max_seg = float(cfg.sector_max_segment_mm)
        cells = int(self.packed.occ.shape[1] * self.packed.occ.shape[2])
        self._path = np.zeros((cells, 2), dtype=np.int64)  # planner scratch
        self._wps = np.zeros((cells, 2))  # the open episode's waypoints (kept across chunks)
        self._rem = np.zeros(cells)

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
                         float(self.cfg.lr), self.lr_end, int(self.cfg.steps), float(self.cfg.gamma),
                         *self._eps, self._rw, self.max_episode_steps, self.hold_max, self._guided,
                         self._clear_r, self._max_seg, self._path, self._wps, self._rem, self.noise_mm,
                         int(start_step), int(n_steps), out_ret, out_succ)
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


def seek_table(encoder: SectorEncoder) -> np.ndarray:
    """The hand-written baseline as a Q table: forward when the target is in
    the bearing sector straight ahead, else turn toward it (ranges ignored)."""
    q = np.zeros((encoder.n_states, encoder.n_actions))
    per = encoder.nbins ** len(encoder.sensors)
    n = encoder.bearing_sectors
    for b in range(n):
        a = 0 if b == 0 else (1 if b <= n // 2 else 2)  # sectors count counter-clockwise
        q[b * per:(b + 1) * per, a] = 1.0
    return q


def plan_pairs(gridmap: GridMap, starts: np.ndarray, goals: np.ndarray, dists: np.ndarray,
               slot: np.ndarray, margin_mm: float = DEFAULT_MARGIN_MM,
               max_segment_mm: float = DEFAULT_MAX_SEGMENT_MM):
    """Waypoints for every distinct (start cell, goal cell) of an episode
    list, planned from the start cell's centre: (wp_all (P, K, 2), nwp (P,),
    rem (P, K), pair index per episode)."""
    from ground_station.maps.planner import remaining_lengths

    occ, h, w, c = grid_of(gridmap)
    key = np.concatenate([starts, goals], axis=1)
    ukey, first, pair = np.unique(key, axis=0, return_index=True, return_inverse=True)
    pair = pair.reshape(-1).astype(np.int64)
    p = len(ukey)
    kmax = h * w
    wp_all = np.zeros((max(p, 1), kmax, 2))
    rem_all = np.zeros((max(p, 1), kmax))
    nwp = np.zeros(max(p, 1), dtype=np.int64)
    scratch = np.zeros((kmax, 2), dtype=np.int64)
    r = clearance_mm(margin_mm)
    for j in range(p):
        e = first[j]
        sx, sy = (starts[e, 0] + 0.5) * c, (h - starts[e, 1] - 0.5) * c
        nwp[j] = plan_into(occ, h, w, c, dists[slot[e]], sx, sy, r, float(max_segment_mm), scratch, wp_all[j])
        remaining_lengths(wp_all[j], nwp[j], rem_all[j])
    return wp_all, nwp, rem_all, pair


def _rollouts(q, gridmap, encoder, starts, goals, hidx, headings, guidance, max_steps, stall_steps,
              margin_mm, max_segment_mm) -> dict:
    n = len(starts)
    occ, h, w, c = grid_of(gridmap)
    ugoals, slot = np.unique(goals, axis=0, return_inverse=True)
    slot = slot.reshape(-1).astype(np.int64)
    dists = np.stack([octile_distances(gridmap.occ, int(gc), int(gr)) for gc, gr in ugoals]) \
        if n else np.zeros((0, h, w))
    guided = check_guidance(guidance)
    if guided and n:
        wp_all, nwp, rem_all, pair = plan_pairs(gridmap, starts, goals, dists, slot, margin_mm, max_segment_mm)
    else:
        wp_all, nwp, rem_all = np.zeros((1, 1, 2)), np.ones(1, dtype=np.int64), np.zeros((1, 1))
        pair = np.zeros(n, dtype=np.int64)
    sectors, sensors, edges, which = encoder_arrays(encoder)
    outcome = np.zeros(n, dtype=np.int64)
    path = np.zeros(n)
    steps = np.zeros(n, dtype=np.int64)
    th = hidx.astype(np.float64) * (2.0 * math.pi / headings)
    th = (th + math.pi) % (2.0 * math.pi) - math.pi
    eval_kernel(np.ascontiguousarray(q, dtype=np.float64), occ, h, w, c, dists, starts, goals, slot,
                th, sectors, sensors, edges, which, int(max_steps or 0), 400.0, 4.0,
                int(stall_steps), guided, wp_all, nwp, rem_all, pair, outcome, path, steps)
    shortest = dists[slot, starts[:, 1], starts[:, 0]] * c
    ok = outcome == SUCCESS
    ratios = path[ok] / shortest[ok]
    return {
        "success_rate": float(ok.mean()) if n else 0.0,
        "path_ratio_mean": float(ratios.mean()) if ratios.size else float("nan"),
        "path_ratio_max": float(ratios.max()) if ratios.size else float("nan"),
        "path_ratio_median": float(np.median(ratios)) if ratios.size else float("nan"),
        "timeouts": int((outcome == TIMEOUT).sum()),
        "collisions": int((outcome == COLLISION).sum()),
        "loops": int((outcome == LOOP).sum()),
        "mean_steps": float(steps.mean()) if n else 0.0,
    }


def evaluate_sector(q: np.ndarray, gridmap: GridMap, encoder: SectorEncoder, seed: int = 0,
                    sample: int | None = None, max_steps: int | None = None, headings: int = 8,
                    stall_steps: int = 400, guidance: str = "path", direct: bool = False,
                    baseline: bool = False, margin_mm: float = DEFAULT_MARGIN_MM,
                    max_segment_mm: float = DEFAULT_MAX_SEGMENT_MM) -> dict:
    """Greedy rollouts of q over (start, goal, heading) on gridmap.

    Starts at cell centres with headings k*2pi/headings; goals at cell
    centres (reached within robot.GOAL_TOLERANCE_MM). guidance "path": the
    robot follows the planner's waypoints from the start cell's centre
    (`ground_station.maps.planner.plan_waypoints` with margin_mm /
    max_segment_mm), each passed within GOAL_TOLERANCE_MM as the controller
    does; "direct": the bearing is the goal's. Step budget per episode:
    max_steps if given, else 400 + 4 x the octile shortest path in forward
    control periods. Path ratio = driven length / octile shortest length
    between the cell centres, over successful episodes. A loop is an episode
    whose guide potential found no new minimum for `stall_steps` periods.

    The main keys are the `guidance` figures; `direct=True` adds the same
    figures without guidance as `direct_<key>` (and as a dict under
    "direct"); `baseline=True` adds the hand-written `seek_table` under the
    main guidance as `baseline_<key>` (and under "baseline")."""
    if q.shape != (encoder.n_states, encoder.n_actions):
        raise ValueError(f"q shape {q.shape} does not match the encoder's "
                         f"({encoder.n_states}, {encoder.n_actions})")
    check_guidance(guidance)
    starts, goals, hidx = eval_episodes(gridmap, seed=seed, sample=sample, headings=headings)
    args = (starts, goals, hidx, headings)
    extra = (max_steps, stall_steps, margin_mm, max_segment_mm)
    rep = {"map": gridmap.name, "episodes": int(len(starts)), "guidance": guidance,
           **_rollouts(q, gridmap, encoder, *args, guidance, *extra)}
    if direct:
        d = _rollouts(q, gridmap, encoder, *args, "direct", *extra)
        rep.update({f"direct_{k}": v for k, v in d.items()})
        rep["direct"] = {**d, "episodes": rep["episodes"]}
    if baseline:
        b = _rollouts(seek_table(encoder), gridmap, encoder, *args, guidance, *extra)
        rep.update({f"baseline_{k}": v for k, v in b.items()})
        rep["baseline"] = {**b, "episodes": rep["episodes"]}
    rep.update({"headings": int(headings), "sample": sample, "seed": int(seed)})
    if guidance == "path":
        rep.update({"margin_mm": float(margin_mm), "max_segment_mm": float(max_segment_mm)})
    return rep
