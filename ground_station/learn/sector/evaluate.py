"""Greedy evaluation of a sector table on the kinematic twin.

`evaluate_sector`: greedy rollouts (the kernels' `eval_kernel`) from every
(start cell centre, goal cell, heading) of a map, or a seeded sample. It reads
only a table and a map, so it judges saved runs and exported policies alike
(`qnav eval`, `qnav export`).
"""

from __future__ import annotations

import math

import numpy as np

from firmware_py.kinds.sector.encoder import SectorEncoder
from ground_station.learn.sector.kernels import COLLISION, LOOP, SUCCESS, TIMEOUT, eval_kernel
from ground_station.learn.sector.reward import check_guidance
from ground_station.learn.sector.twin import TwinRobot, encoder_arrays, grid_of
from ground_station.maps import GridMap, octile_distances
from ground_station.maps.planner import (
    DEFAULT_MARGIN_MM,
    DEFAULT_MAX_SEGMENT_MM,
    clearance_mm,
    guidance_from_metadata,
    plan_into,
    remaining_lengths,
)


def eval_episodes(gridmap: GridMap, seed: int = 0, sample: int | None = None,
                  headings: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(starts, goals, heading indices): every ordered pair of distinct connected free cells x
    `headings` headings, or a seeded sample of `sample` of them."""
    cells = np.array(gridmap.free_cells(), dtype=np.int64)
    n = len(cells)
    grid_s, grid_g = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    si, gi = grid_s.ravel(), grid_g.ravel()
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
    """The hand-written baseline: forward when the target is straight ahead, else turn toward it."""
    q = np.zeros((encoder.n_states, encoder.n_actions))
    per = encoder.nbins ** len(encoder.sensors)
    n = encoder.bearing_sectors
    for b in range(n):
        a = 0 if b == 0 else (1 if b <= n // 2 else 2)  # sectors count counter-clockwise
        q[b * per:(b + 1) * per, a] = 1.0
    return q


def plan_pairs(gridmap: GridMap, starts: np.ndarray, goals: np.ndarray, dists: np.ndarray,
               slot: np.ndarray, margin_mm: float = DEFAULT_MARGIN_MM,
               max_segment_mm: float = DEFAULT_MAX_SEGMENT_MM, radius_mm: float = TwinRobot().radius_mm):
    """Waypoints of every distinct (start cell, goal cell), planned from the start cell's centre:
    (wp_all (P, K, 2), nwp (P,), rem (P, K), pair index per episode)."""
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
    r = clearance_mm(margin_mm, radius_mm)
    for j in range(p):
        e = first[j]
        sx, sy = (starts[e, 0] + 0.5) * c, (h - starts[e, 1] - 0.5) * c
        nwp[j] = plan_into(occ, h, w, c, dists[slot[e]], sx, sy, r, float(max_segment_mm), scratch, wp_all[j])
        remaining_lengths(wp_all[j], nwp[j], rem_all[j])
    return wp_all, nwp, rem_all, pair


def _rollouts(q, gridmap, encoder, starts, goals, hidx, headings, guidance, max_steps, stall_steps,
              margin_mm, max_segment_mm, robot) -> dict:
    n = len(starts)
    occ, h, w, c = grid_of(gridmap)
    ugoals, slot = np.unique(goals, axis=0, return_inverse=True)
    slot = slot.reshape(-1).astype(np.int64)
    dists = np.stack([octile_distances(gridmap.occ, int(gc), int(gr)) for gc, gr in ugoals]) \
        if n else np.zeros((0, h, w))
    guided = check_guidance(guidance)
    if guided and n:
        wp_all, nwp, rem_all, pair = plan_pairs(gridmap, starts, goals, dists, slot, margin_mm, max_segment_mm,
                                                robot.radius_mm)
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
                int(stall_steps), guided, wp_all, nwp, rem_all, pair, outcome, path, steps, robot.arrays())
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
                    max_segment_mm: float = DEFAULT_MAX_SEGMENT_MM, robot: TwinRobot | None = None) -> dict:
    """Greedy rollouts of q over (start, goal, heading) on gridmap for the twin of `robot`.

    Starts at cell centres with headings k*2pi/headings; guidance "path" follows the planner's
    waypoints as a mission, "direct" the goal's bearing. Step budget: max_steps, else 400 + 4 x
    the shortest path in forward control periods (`eval_kernel`). Path ratio = driven / octile
    shortest length, over successful episodes.

    The main keys are the `guidance` figures; `direct=True` adds them without guidance as
    `direct_<key>` (and under "direct"), `baseline=True` those of `seek_table` as
    `baseline_<key>` (and under "baseline")."""
    if q.shape != (encoder.n_states, encoder.n_actions):
        raise ValueError(f"q shape {q.shape} does not match the encoder's "
                         f"({encoder.n_states}, {encoder.n_actions})")
    check_guidance(guidance)
    starts, goals, hidx = eval_episodes(gridmap, seed=seed, sample=sample, headings=headings)
    args = (starts, goals, hidx, headings)
    extra = (max_steps, stall_steps, margin_mm, max_segment_mm, robot or TwinRobot())
    rep = {"map": gridmap.name, "episodes": int(len(starts)), "guidance": guidance,
           **_rollouts(q, gridmap, encoder, *args, guidance, *extra)}
    for key, wanted, guide in (("direct", direct, "direct"), ("baseline", baseline, guidance)):
        if wanted:  # the policy without guidance; the seek table guided as the policy
            r = _rollouts(q if key == "direct" else seek_table(encoder), gridmap, encoder, *args, guide, *extra)
            rep.update({f"{key}_{k}": v for k, v in r.items()})
            rep[key] = {**r, "episodes": rep["episodes"]}
    rep.update({"headings": int(headings), "sample": sample, "seed": int(seed)})
    if guidance == "path":
        rep.update({"margin_mm": float(margin_mm), "max_segment_mm": float(max_segment_mm)})
    return rep


def guidance_of(meta: dict) -> dict:
    """evaluate_sector's guidance keywords for a sector run: guided, with the run's own planner."""
    return {"guidance": "path", **guidance_from_metadata(meta)}


def evaluate_policy(q: np.ndarray, run, gridmap: GridMap, *, sample: int | None = None,  # type: ignore[no-untyped-def]
                    seed: int = 0, full: bool = False) -> dict:
    """The kind's evaluation (ground_station.learn.kinds): `evaluate_sector` of a run's table,
    guided as it trained; `full` adds the direct figures and the hand-written seek baseline."""
    return evaluate_sector(q, gridmap, run.encoder, seed=seed, sample=sample, **guidance_of(run.meta),
                           direct=full, baseline=full, robot=TwinRobot.of_meta(run.meta))
