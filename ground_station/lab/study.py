"""The learning-rate and learner study on the cell encoding, and the learner
comparison on the sector encoding, with statistics.

The questions (issue 19): how many training steps does Q-learning need to
reach 95 % greedy success, as a function of the learning rate eta, with and
without the epsilon schedule; what do the Q values do meanwhile (the
paper's Fig. 5: mean max-Q of the visited states against episodes, per
eta); how do the other tabular learners (`ground_station.learn.cell.learners`)
compare; and how does the learnt policy compare with the optimum BFS gives
directly.

Every job is one seeded training run (`run_job`, a module-level function
for `engine.map`): it trains in chunks of `eval_every` steps and after each
chunk rolls the greedy policy out from every (start, goal) pair
(`evaluate.rollouts_cell`) and takes the mean over visited states (rows the
training has changed) of max_a Q. A job's result depends only on its
config, so study.json is identical on every engine; the jobs' own run
times go to campaign.json.

Sector part (`sector_jobs`, `run_sector_job`, with sector_seeds > 0): each
learner trains the shipped sector recipe (`sector_base`, fewer steps) on
the twin, and every eval_every steps its greedy table is rolled out on a
fixed episode sample (`SectorEval`: success, and over the successes the
driven length against the octile grid path and against the disc robot's
any-angle optimum, `ground_station.lab.anyangle`).

Statistics: every figure is a mean over seeds with a bootstrapped 95 %
confidence interval of that mean (percentile bootstrap, `BOOTSTRAP`
resamples, fixed generator seed: the CI is reproducible). Steps to
threshold: the first checkpoint at which greedy success >= threshold; a
run that never reaches it counts as the step budget (a lower bound: the
mean is then censored) and the tables say how many reached it.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ground_station.lab.study_defaults import SECTOR_EVAL_EVERY, SECTOR_SAMPLE, SECTOR_STEPS
from ground_station.learn.config import LEARNERS, TrainConfig

BOOTSTRAP = 4000
CI_SEED = 0


def bootstrap_ci(values: Any, axis: int = -1) -> tuple[Any, Any, Any]:
    """(mean, lo, hi): the mean along `axis` and its bootstrapped 95 % CI
    (percentile method, BOOTSTRAP resamples of the seeds, seed CI_SEED)."""
    x = np.moveaxis(np.asarray(values, dtype=np.float64), axis, -1)
    n = x.shape[-1]
    mean = x.mean(axis=-1)
    if n < 2:
        return mean, mean, mean
    idx = np.random.default_rng(CI_SEED).integers(0, n, (BOOTSTRAP, n))
    means = x[..., idx].mean(axis=-1)  # (..., BOOTSTRAP)
    lo, hi = np.percentile(means, [2.5, 97.5], axis=-1)
    return mean, lo, hi


def _ci(values: list[float]) -> dict:
    m, lo, hi = bootstrap_ci(values)
    return {"mean": round(float(m), 6), "ci95": [round(float(lo), 6), round(float(hi), 6)], "n": len(values)}


# --------------------------------------------------------------------------
# one job: train with greedy checkpoints
# --------------------------------------------------------------------------
def run_job(job: dict) -> dict:
    """Train job["config"] on the cell encoding, evaluating the greedy policy
    every job["eval_every"] steps; the learning curve and steps to threshold."""
    from ground_station.learn.cell.evaluate import POLICY_Q, SUCCESS, rollouts_cell
    from ground_station.learn.cell.learners import CellLearner
    from ground_station.learn.cell.trainer import CellProblem
    from ground_station.learn.train import initial_table
    from ground_station.maps import load_map

    cfg = TrainConfig.of(**job["config"])
    gm = load_map(cfg.map)
    prob = CellProblem.build(gm, cfg.options.targets or None)
    q0 = initial_table(cfg, prob.encoder.n_states, prob.encoder.n_actions)
    lrn = CellLearner(cfg, prob, q0.copy())
    pair_goal, pair_start = (a.astype(np.int64) for a in np.nonzero(prob.dist > 0))
    shortest = prob.dist[pair_goal, pair_start]
    limit = gm.width * gm.height
    every = int(job["eval_every"])
    steps, episodes, success, qmax = [], [], [], []
    n_ep = 0
    train_s = 0.0
    reached = None
    out = steps_ok = None
    while lrn.done < cfg.steps:
        t0 = time.perf_counter()
        rets, _ = lrn.run(min(every, cfg.steps - lrn.done))
        train_s += time.perf_counter() - t0
        n_ep += len(rets)
        table = np.ascontiguousarray(lrn.table())
        out, steps_ok = rollouts_cell(table, prob.next_cell, gm.width, prob.goal_cells, pair_goal, pair_start,
                                      limit, POLICY_Q)
        sr = float((out == SUCCESS).mean())
        visited = np.any(table != q0, axis=1)
        steps.append(lrn.done)
        episodes.append(n_ep)
        success.append(round(sr, 6))
        qmax.append(round(float(table[visited].max(axis=1).mean()) if visited.any() else 0.0, 9))
        if reached is None and sr >= job["threshold"]:
            reached = lrn.done
    assert out is not None and steps_ok is not None
    ok = out == SUCCESS
    return {"group": job["group"], "learner": cfg.learner, "lr": cfg.lr, "schedule": job["schedule"],
            "seed": cfg.seed, "steps_to_threshold": reached, "final_success": success[-1],
            "final_path_ratio": round(float((steps_ok[ok] / shortest[ok]).mean()), 6) if ok.any() else None,
            "curve": {"steps": steps, "episodes": episodes, "success": success, "qmax": qmax},
            "train_seconds": train_s}


# --------------------------------------------------------------------------
# the job list and the summary
# --------------------------------------------------------------------------
def study_jobs(base: TrainConfig, lrs: list[float], seeds: int, constant_epsilon: float,
               learners: list[str], learner_lrs: list[float], eval_every: int, threshold: float) -> list[dict]:
    """lr x schedule x seed Q-learning runs, then learner x learner_lr x seed runs
    (seeds base.seed .. base.seed + seeds - 1)."""
    def job(group: str, schedule: str, cfg: TrainConfig) -> dict:
        return {"group": group, "schedule": schedule, "config": cfg.flat(), "eval_every": eval_every,
                "threshold": threshold}

    q = replace(base, learner="q")
    const = replace(q, epsilon_start=constant_epsilon, epsilon_end=constant_epsilon)
    jobs = [job("lr", name, replace(c, lr=lr, seed=base.seed + k))
            for name, c in (("decay", q), ("constant", const)) for lr in lrs for k in range(seeds)]
    jobs += [job("learner", "decay", replace(base, learner=learner, lr=lr, seed=base.seed + k))
             for learner in learners for lr in learner_lrs for k in range(seeds)]
    return jobs


def _threshold_stats(rs: list[dict], budget: int) -> dict:
    vals = [r["steps_to_threshold"] if r["steps_to_threshold"] is not None else budget for r in rs]
    return {**_ci(vals), "reached": sum(r["steps_to_threshold"] is not None for r in rs)}


def _curve_stats(rs: list[dict]) -> dict:
    n = min(len(r["curve"]["steps"]) for r in rs)
    out: dict[str, Any] = {"steps": rs[0]["curve"]["steps"][:n],
                           "episodes": [round(float(v), 2) for v in
                                        np.mean([r["curve"]["episodes"][:n] for r in rs], axis=0)]}
    for key in ("success", "qmax"):
        m, lo, hi = bootstrap_ci(np.array([r["curve"][key][:n] for r in rs]), axis=0)
        out[key] = {"mean": np.round(m, 6).tolist(), "lo": np.round(lo, 6).tolist(), "hi": np.round(hi, 6).tolist()}
    return out


def summarise(results: list[dict], lrs: list[float], learners: list[str], learner_lrs: list[float],
              budget: int) -> dict:
    """Per (schedule, eta) and per (learner, eta): means with bootstrapped 95 % CIs."""
    lr_rows = []
    for schedule in ("decay", "constant"):
        for lr in lrs:
            rs = [r for r in results if r["group"] == "lr" and r["schedule"] == schedule and r["lr"] == lr]
            lr_rows.append({"schedule": schedule, "lr": lr, "steps_to_threshold": _threshold_stats(rs, budget),
                            "final_success": _ci([r["final_success"] for r in rs]), "curve": _curve_stats(rs)})
    learner_rows = []
    for learner in learners:
        for lr in learner_lrs:
            rs = [r for r in results if r["group"] == "learner" and r["learner"] == learner and r["lr"] == lr]
            ratios = [r["final_path_ratio"] for r in rs if r["final_path_ratio"] is not None]
            learner_rows.append({"learner": learner, "lr": lr, "steps_to_threshold": _threshold_stats(rs, budget),
                                 "final_success": _ci([r["final_success"] for r in rs]),
                                 "final_path_ratio": _ci(ratios) if ratios else None})
    return {"lr_study": lr_rows, "learners": learner_rows}


# --------------------------------------------------------------------------
# the learners on the sector encoding (the kinematic twin)
# --------------------------------------------------------------------------


def sector_base(base: TrainConfig, steps: int = SECTOR_STEPS) -> TrainConfig:
    """The shipped sector recipe (`ground_station.learn.sector.KIND.recipe`) on base's map and seed, with `steps`."""
    from ground_station.learn.config import recipe_config

    return recipe_config("sector", {"map": base.map, "seed": base.seed, "steps": steps,
                                    "learner_lambda": base.learner_lambda, "trace_min": base.trace_min,
                                    "dyna_planning": base.dyna_planning})


def sector_jobs(sbase: TrainConfig, learners: list[str], seeds: int, eval_every: int, threshold: float,
                sample: int) -> list[dict]:
    """learner x seed runs of the sector recipe (seeds sbase.seed .. + seeds - 1)."""
    return [{"group": "sector", "schedule": "decay", "config": replace(sbase, learner=learner,
                                                                            seed=sbase.seed + k).flat(),
             "eval_every": eval_every, "threshold": threshold, "sample": sample}
            for learner in learners for k in range(seeds)]


class SectorEval:
    """The fixed greedy evaluation of a sector study run: `sample` episodes
    (`sector.evaluate.eval_episodes`, seed 0) on the recipe's guidance
    (waypoints planned once), and each episode's any-angle optimum for the
    disc robot (`ground_station.lab.anyangle`)."""

    def __init__(self, gridmap: Any, cfg: TrainConfig, sample: int) -> None:
        import math

        from firmware_py import robot_spec
        from ground_station.lab.anyangle import anyangle_distances
        from ground_station.learn.sector.evaluate import eval_episodes, plan_pairs
        from ground_station.learn.sector.reward import check_guidance
        from ground_station.learn.sector.twin import grid_of
        from ground_station.maps import octile_distances

        self.headings = 8
        starts, goals, hidx = eval_episodes(gridmap, seed=0, sample=sample, headings=self.headings)
        self.occ, self.h, self.w, self.c = grid_of(gridmap)
        ugoals, slot = np.unique(goals, axis=0, return_inverse=True)
        self.slot = slot.reshape(-1).astype(np.int64)
        self.dists = np.stack([octile_distances(gridmap.occ, int(gc), int(gr)) for gc, gr in ugoals])
        self.guided = check_guidance(cfg.options.guidance)
        if self.guided:
            self.wp, self.nwp, self.rem, self.pair = plan_pairs(gridmap, starts, goals, self.dists, self.slot,
                                                                cfg.options.margin_mm, cfg.options.max_segment_mm)
        else:
            self.wp, self.nwp, self.rem = np.zeros((1, 1, 2)), np.ones(1, dtype=np.int64), np.zeros((1, 1))
            self.pair = np.zeros(len(starts), dtype=np.int64)
        th = hidx.astype(np.float64) * (2.0 * math.pi / self.headings)
        self.th = (th + math.pi) % (2.0 * math.pi) - math.pi
        self.starts, self.goals = starts, goals
        self.octile = self.dists[self.slot, starts[:, 1], starts[:, 0]] * self.c
        cells, dmat = anyangle_distances(gridmap, float(robot_spec.ROBOT_RADIUS_MM))
        index = {(int(a), int(b)): i for i, (a, b) in enumerate(cells)}
        si = np.array([index[(int(a), int(b))] for a, b in starts])
        gi = np.array([index[(int(a), int(b))] for a, b in goals])
        # the robot is done within the goal tolerance: the optimum of the task ends that much early
        self.anyangle = dmat[si, gi] - float(robot_spec.GOAL_TOLERANCE_MM)

    def __call__(self, q: np.ndarray, encoder: Any) -> dict:
        """Greedy success and the mean path ratios over the successes."""
        from ground_station.learn.sector.kernels import SUCCESS

        outcome, path = self.rollouts(q, encoder)
        ok = outcome == SUCCESS
        return {"success": float(ok.mean()),
                "octile_ratio": float((path[ok] / self.octile[ok]).mean()) if ok.any() else None,
                "anyangle_ratio": float((path[ok] / self.anyangle[ok]).mean()) if ok.any() else None}

    def rollouts(self, q: np.ndarray, encoder: Any) -> tuple[np.ndarray, np.ndarray]:
        """(outcome, driven mm) of every episode (`sector.kernels.eval_kernel`)."""
        from ground_station.learn.sector.kernels import eval_kernel
        from ground_station.learn.sector.twin import DEFAULT_TW, encoder_arrays

        n = len(self.starts)
        sectors, sensors, edges, which = encoder_arrays(encoder)
        outcome = np.zeros(n, dtype=np.int64)
        path = np.zeros(n)
        steps = np.zeros(n, dtype=np.int64)
        eval_kernel(np.ascontiguousarray(q, dtype=np.float64), self.occ, self.h, self.w, self.c, self.dists,
                    self.starts, self.goals, self.slot, self.th, sectors, sensors, edges, which, 0, 400.0, 4.0,
                    400, self.guided, self.wp, self.nwp, self.rem, self.pair, outcome, path, steps, DEFAULT_TW)
        return outcome, path


def run_sector_job(job: dict) -> dict:
    """Train job["config"] (sector encoding) with its learner, evaluating the
    greedy policy every job["eval_every"] steps on `SectorEval`."""
    from ground_station.learn.sector.trainer import SectorTrainer, sector_encoder
    from ground_station.learn.train import initial_table
    from ground_station.maps import load_map

    cfg = TrainConfig.of(**job["config"])
    gm = load_map(cfg.map)
    trainer = SectorTrainer([gm], cfg, sector_encoder(cfg))
    ev = SectorEval(gm, cfg, int(job["sample"]))
    q = initial_table(cfg, trainer.n_states, trainer.n_actions)
    every = int(job["eval_every"])
    done = 0
    train_s = 0.0
    steps, success = [], []
    reached = None
    res: dict = {}
    while done < cfg.steps:
        n = min(every, cfg.steps - done)
        t0 = time.perf_counter()
        trainer.run(q, done, n)
        train_s += time.perf_counter() - t0
        done += n
        res = ev(trainer.table(q), trainer.encoder)
        steps.append(done)
        success.append(round(res["success"], 6))
        if reached is None and res["success"] >= job["threshold"]:
            reached = done
    rnd = {k: (round(v, 6) if v is not None else None) for k, v in res.items()}
    return {"group": "sector", "learner": cfg.learner, "lr": cfg.lr, "schedule": "decay", "seed": cfg.seed,
            "steps_to_threshold": reached, "final_success": success[-1],
            "final_path_ratio": rnd["octile_ratio"], "final_anyangle_ratio": rnd["anyangle_ratio"],
            "curve": {"steps": steps, "success": success}, "train_seconds": train_s}


def summarise_sector(results: list[dict], learners: list[str], budget: int) -> list[dict]:
    """Per learner: final success, steps to threshold, path ratios (octile and
    any-angle), means with bootstrapped 95 % CIs over the seeds."""
    rows = []
    for learner in learners:
        rs = [r for r in results if r["group"] == "sector" and r["learner"] == learner]
        if not rs:
            continue
        row: dict[str, Any] = {"learner": learner, "steps_to_threshold": _threshold_stats(rs, budget),
                               "final_success": _ci([r["final_success"] for r in rs])}
        for key in ("final_path_ratio", "final_anyangle_ratio"):
            vals = [r[key] for r in rs if r[key] is not None]
            row[key] = _ci(vals) if vals else None
        n = min(len(r["curve"]["steps"]) for r in rs)
        m, lo, hi = bootstrap_ci(np.array([r["curve"]["success"][:n] for r in rs]), axis=0)
        row["curve"] = {"steps": rs[0]["curve"]["steps"][:n], "success": {
            "mean": np.round(m, 6).tolist(), "lo": np.round(lo, 6).tolist(), "hi": np.round(hi, 6).tolist()}}
        rows.append(row)
    return rows


# --------------------------------------------------------------------------
# the optimum beside it: BFS
# --------------------------------------------------------------------------
def optimum(base: TrainConfig) -> tuple[dict, dict]:
    """Greedy policy of the shipped cell recipe (the TrainConfig defaults: eta
    0.5, 3M steps) on base's map, targets and seed, against BFS on the same
    pairs: (deterministic part for study.json, timings for campaign.json;
    each time the best of 3 after a warm-up call)."""
    from ground_station.learn.cell.evaluate import POLICY_Q, SUCCESS, rollouts_cell
    from ground_station.learn.cell.trainer import CellProblem, train_cell
    from ground_station.learn.envs.cell_env import goal_distances
    from ground_station.maps import load_map

    gm = load_map(base.map)
    cfg = TrainConfig.of(map=base.map, targets=base.options.targets, seed=base.seed)
    res = min((train_cell(cfg, gm) for _ in range(3)), key=lambda r: r.seconds)
    prob = CellProblem.build(gm, cfg.options.targets or None)
    free = [(c, r) for r in range(gm.height) for c in range(gm.width) if gm.is_free(c, r)]
    pair_goal, pair_start = (a.astype(np.int64) for a in np.nonzero(prob.dist > 0))

    def rollouts() -> tuple[np.ndarray, np.ndarray]:
        return rollouts_cell(np.ascontiguousarray(res.q), prob.next_cell, gm.width, prob.goal_cells,
                             pair_goal, pair_start, gm.width * gm.height, POLICY_Q)

    bfs_goals_s = _best_time(lambda: goal_distances(gm, prob.goals))  # what the table encodes
    bfs_all_s = _best_time(lambda: goal_distances(gm, free))  # all pairs
    rollout_s = _best_time(rollouts)
    out, steps = rollouts()
    shortest = prob.dist[pair_goal, pair_start]
    ok = out == SUCCESS
    # the longest shortest pair: the greedy path drawn beside a BFS shortest path
    i = int(np.argmax(np.where(ok, shortest, -1)))
    det = {"config": {"lr": cfg.lr, "steps": cfg.steps, "seed": cfg.seed}, "pairs": int(len(out)),
           "success": float(ok.mean()),
           "path_ratio_mean": float((steps[ok] / shortest[ok]).mean()) if ok.any() else None,
           "path_ratio_max": float((steps[ok] / shortest[ok]).max()) if ok.any() else None,
           "example": {"goal": prob.target_names[int(pair_goal[i])], "start_cell": int(pair_start[i]),
                       "greedy_steps": int(steps[i]), "bfs_steps": int(shortest[i]),
                       "greedy_path": _greedy_path(res.q, prob, int(pair_goal[i]), int(pair_start[i])),
                       "bfs_path": _bfs_path(prob.dist[int(pair_goal[i])], prob.next_cell, int(pair_start[i]))}}
    timing = {"train_s": round(res.seconds, 6), "greedy_rollouts_s": round(rollout_s, 6),
              "bfs_goals_s": round(bfs_goals_s, 6), "bfs_all_pairs_s": round(bfs_all_s, 6),
              "free_cells": len(free)}
    return det, timing


def _best_time(fn: Any) -> float:
    fn()  # warm-up: numba loads its cache on the first call
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def _greedy_path(q: np.ndarray, prob: Any, g: int, cell: int) -> list[int]:
    n_cells = prob.next_cell.shape[0]
    path = [cell]
    while cell != prob.goal_cells[g] and len(path) <= n_cells:
        cell = int(prob.next_cell[cell, int(np.argmax(q[g * n_cells + cell]))])
        if cell < 0:
            break
        path.append(cell)
    return path


def _bfs_path(dist: np.ndarray, next_cell: np.ndarray, cell: int) -> list[int]:
    path = [cell]
    while dist[cell] > 0:
        cell = next(int(c) for c in next_cell[cell] if c >= 0 and dist[c] == dist[cell] - 1)
        path.append(cell)
    return path


# --------------------------------------------------------------------------
# the whole study
# --------------------------------------------------------------------------
def run_any_job(job: dict) -> dict:
    """`run_sector_job` for the sector runs, `run_job` for the cell runs."""
    return run_sector_job(job) if job["group"] == "sector" else run_job(job)


def study(base: TrainConfig, lrs: list[float], seeds: int, *, constant_epsilon: float = 0.1,
          learners: list[str] | None = None, learner_lrs: list[float] | None = None, eval_every: int = 1000,
          threshold: float = 0.95, sector_learners: list[str] | None = None, sector_seeds: int = 0,
          sector_steps: int = SECTOR_STEPS, sector_eval_every: int = SECTOR_EVAL_EVERY,
          sector_sample: int = SECTOR_SAMPLE, engine: Any = None, progress: bool = False) -> dict:
    """Run every job on `engine` (default: local pool); the result and, under
    "campaign", what it cost (kept apart by `write_study`). sector_seeds > 0
    adds the learner comparison on the sector encoding (`sector_base`: the
    shipped recipe with sector_steps) under "sector"."""
    from ground_station.lab.campaign.engines import LocalEngine

    learners = list(learners or LEARNERS)
    learner_lrs = list(learner_lrs or [base.lr])
    sector_learners = list(sector_learners or LEARNERS)
    jobs = study_jobs(base, lrs, seeds, constant_epsilon, learners, learner_lrs, eval_every, threshold)
    sbase = sector_base(base, sector_steps)
    if sector_seeds > 0:
        jobs += sector_jobs(sbase, sector_learners, sector_seeds, sector_eval_every, threshold, sector_sample)
    engine = engine or LocalEngine()
    results, stats = engine.map(run_any_job, jobs, desc="study", progress=progress, unit="run")
    seconds = [r.pop("train_seconds") for r in results]
    opt, opt_timing = optimum(base)
    wall = {f"{learner} lr={lr:g}": _ci([s for r, s in zip(results, seconds, strict=True)
                                         if r["group"] == "learner" and r["learner"] == learner and r["lr"] == lr])
            for learner in learners for lr in learner_lrs}
    campaign = {**stats.as_dict(), "train_seconds_total": round(sum(seconds), 3),
                "learner_train_seconds": wall, "optimum": opt_timing}
    cell_results = [r for r in results if r["group"] != "sector"]
    out = {"map": base.map, "encoding": "cell", "targets": base.options.targets, "seeds": seeds, "lrs": lrs,
           "constant_epsilon": constant_epsilon, "learners": learners, "learner_lrs": learner_lrs,
           "eval_every": eval_every, "threshold": threshold, "ci": f"bootstrapped 95 % CI of the mean over seeds "
           f"(percentile, {BOOTSTRAP} resamples)", "config": base.flat(),
           **summarise(cell_results, lrs, learners, learner_lrs, base.steps), "optimum": opt}
    if sector_seeds > 0:
        campaign["sector_train_seconds"] = {
            learner: _ci([s for r, s in zip(results, seconds, strict=True)
                          if r["group"] == "sector" and r["learner"] == learner]) for learner in sector_learners}
        out["sector"] = {"map": sbase.map, "seeds": sector_seeds, "learners": sector_learners,
                         "steps": sector_steps, "eval_every": sector_eval_every, "sample": sector_sample,
                         "guidance": sbase.options.guidance, "config": sbase.flat(),
                         "rows": summarise_sector(results, sector_learners, sector_steps)}
    out["runs"] = [{k: v for k, v in r.items() if k != "curve"} for r in results]
    out["campaign"] = campaign
    return out


# --------------------------------------------------------------------------
# figure and files
# --------------------------------------------------------------------------
CI_LABEL = "mean, bootstrapped 95 % CI"


def _panel_threshold(ax: Any, data: dict) -> None:
    """Steps to the threshold against eta, with and without the epsilon schedule."""
    n, thr = data["seeds"], data["threshold"]
    for schedule, color in (("decay", "tab:blue"), ("constant", "tab:orange")):
        rows = [r for r in data["lr_study"] if r["schedule"] == schedule]
        m = np.array([r["steps_to_threshold"]["mean"] for r in rows])
        lo = np.array([r["steps_to_threshold"]["ci95"][0] for r in rows])
        hi = np.array([r["steps_to_threshold"]["ci95"][1] for r in rows])
        lab = ("epsilon 1 -> {:g} over {:g} of the steps".format(data["config"]["epsilon_end"],
                                                                 data["config"]["epsilon_decay"])
               if schedule == "decay" else f"constant epsilon {data['constant_epsilon']:g}")
        ax.errorbar([r["lr"] for r in rows], m, yerr=[m - lo, hi - m], marker="o", capsize=3, color=color, label=lab)
    ax.set_xlabel("learning rate eta")
    ax.set_ylabel(f"training steps to {thr:.0%} greedy success (budget if never)")
    ax.set_title(f"steps to threshold\n({CI_LABEL}, {n} seeds)")
    ax.legend(fontsize=8)


def _panel_per_eta(ax: Any, data: dict, cmap: Any, x: str, y: str) -> None:
    """Curve `y` (mean and CI band) against `x` along training, one line per eta, epsilon schedule."""
    decay = [r for r in data["lr_study"] if r["schedule"] == "decay"]
    for i, r in enumerate(decay):
        c, col = r["curve"], cmap(i / max(1, len(decay) - 1))
        ax.plot(c[x], c[y]["mean"], color=col, label=f"eta={r['lr']:g}")
        ax.fill_between(c[x], c[y]["lo"], c[y]["hi"], color=col, alpha=0.2)
    ax.legend(fontsize=7, ncol=2)


def _panel_success(ax: Any, data: dict, cmap: Any) -> None:
    """Greedy success along training per eta (epsilon schedule)."""
    _panel_per_eta(ax, data, cmap, "steps", "success")
    ax.axhline(data["threshold"], color="grey", linestyle=":")
    ax.set_xlabel("training steps")
    ax.set_ylabel("greedy success, all (start, goal) pairs")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"greedy success, epsilon schedule\n({CI_LABEL}, {data['seeds']} seeds)")


def _panel_q(ax: Any, data: dict, cmap: Any) -> None:
    """Mean max-Q of the visited states along training per eta: the paper's Fig. 5."""
    _panel_per_eta(ax, data, cmap, "episodes", "qmax")
    ax.set_xlabel("episode")
    ax.set_ylabel("mean max_a Q(s, a) over visited states")
    ax.set_title(f"Q values, the paper's Fig. 5, epsilon schedule\n({CI_LABEL}, {data['seeds']} seeds)")


def plot_curves(data: dict) -> bytes:
    """PNG, three panels of `plot_study`'s Q-learning part: steps to threshold
    against eta (both schedules), greedy success and the Fig. 5 Q values along
    training per eta (`qnav sweep`'s curves.png)."""
    from ground_station.plotting import png_bytes, pyplot

    plt = pyplot()
    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(18, 5.5), dpi=90)
    cmap = plt.get_cmap("viridis")
    _panel_threshold(a1, data)
    _panel_success(a2, data, cmap)
    _panel_q(a3, data, cmap)
    fig.suptitle(f"Q-learning, cell encoding on {data['map']}, {data['config']['steps']:,} steps per run: "
                 f"{data['seeds']} seeds per point; intervals are bootstrapped 95 % confidence intervals of the mean")
    fig.tight_layout()
    return png_bytes(fig)


def plot_study(data: dict) -> bytes:
    """PNG, six panels: steps to threshold vs eta (both schedules); greedy
    success vs steps per eta; mean max-Q of visited states vs episodes per
    eta (Fig. 5); learners' steps to threshold; learners' training time;
    greedy path vs BFS shortest path."""
    from ground_station.maps import load_map
    from ground_station.plotting import png_bytes, pyplot

    plt = pyplot()
    sector = "sector" in data
    fig, axes = plt.subplots(3 if sector else 2, 3, figsize=(18, 15 if sector else 10), dpi=90)
    (a1, a2, a3), (a4, a5, a6) = axes[0], axes[1]
    if sector:
        _plot_sector(data, axes[2], plt)
    cmap = plt.get_cmap("viridis")
    n, thr = data["seeds"], data["threshold"]
    ci = CI_LABEL
    _panel_threshold(a1, data)
    _panel_success(a2, data, cmap)
    _panel_q(a3, data, cmap)
    rows = data["learners"]
    names = [f"{r['learner']}\neta={r['lr']:g}" for r in rows]
    x = np.arange(len(rows))
    m = np.array([r["steps_to_threshold"]["mean"] for r in rows])
    lo = np.array([r["steps_to_threshold"]["ci95"][0] for r in rows])
    hi = np.array([r["steps_to_threshold"]["ci95"][1] for r in rows])
    a4.bar(x, m, yerr=[m - lo, hi - m], capsize=3, color="tab:green")
    for xi, r in zip(x, rows, strict=True):
        a4.text(xi, m[xi], f"{r['steps_to_threshold']['reached']}/{n}", ha="center", va="bottom", fontsize=7)
    a4.set_xticks(x, names, fontsize=7, rotation=45)
    a4.set_ylabel(f"steps to {thr:.0%} greedy success (budget if never; reached/seeds on top)")
    a4.set_title(f"learners, epsilon schedule\n({ci}, {n} seeds)")
    wall = data.get("campaign", {}).get("learner_train_seconds")
    if wall:
        keys = [f"{r['learner']} lr={r['lr']:g}" for r in rows]
        wm = np.array([wall[key]["mean"] for key in keys]) * 1e3
        wlo = np.array([wall[key]["ci95"][0] for key in keys]) * 1e3
        whi = np.array([wall[key]["ci95"][1] for key in keys]) * 1e3
        a5.bar(x, wm, yerr=[wm - wlo, whi - wm], capsize=3, color="tab:purple")
        a5.set_xticks(x, names, fontsize=7, rotation=45)
        a5.set_ylabel(f"training time per run (ms, {data['config']['steps']:,} steps)")
        a5.set_title(f"learners' kernel time\n({ci}; as measured, shared machine)")
    gm = load_map(data["map"])
    ex = data["optimum"]["example"]
    a6.imshow(gm.occ, cmap="Greys", origin="upper")
    for path, style, lab in ((ex["bfs_path"], "-", f"BFS shortest ({ex['bfs_steps']} steps)"),
                             (ex["greedy_path"], "--", f"greedy Q ({ex['greedy_steps']} steps)")):
        a6.plot([c % gm.width for c in path], [c // gm.width for c in path], style, linewidth=2, label=lab)
    t = data.get("campaign", {}).get("optimum")
    title = f"to {ex['goal']}: path ratio over all pairs {data['optimum']['path_ratio_mean']:.3f}"
    if t:
        title += (f"\ntrain {t['train_s'] * 1e3:.1f} ms + rollouts {t['greedy_rollouts_s'] * 1e3:.2f} ms; "
                  f"BFS to the goals {t['bfs_goals_s'] * 1e3:.2f} ms, all pairs {t['bfs_all_pairs_s'] * 1e3:.1f} ms")
    a6.set_title(title, fontsize=9)
    a6.legend(fontsize=8)
    fig.suptitle(f"cell encoding on {data['map']}: {n} seeds per point; intervals are bootstrapped 95 % "
                 f"confidence intervals of the mean")
    fig.tight_layout()
    return png_bytes(fig)


def _plot_sector(data: dict, axes: Any, plt: Any) -> None:
    """Third row: the learners on the sector encoding (success along training,
    steps to threshold, path ratio against the any-angle optimum)."""
    sec = data["sector"]
    rows, n, thr = sec["rows"], sec["seeds"], data["threshold"]
    ci = "mean, bootstrapped 95 % CI"
    b1, b2, b3 = axes
    cmap = plt.get_cmap("tab10")
    for i, r in enumerate(rows):
        c = r["curve"]
        b1.plot(c["steps"], c["success"]["mean"], color=cmap(i), marker=".", label=r["learner"])
        b1.fill_between(c["steps"], c["success"]["lo"], c["success"]["hi"], color=cmap(i), alpha=0.15)
    b1.axhline(thr, color="grey", linestyle=":")
    b1.set_xlabel("training steps (control periods)")
    b1.set_ylabel(f"greedy success, {sec['sample']} episodes ({sec['guidance']})")
    b1.set_title(f"sector encoding on {sec['map']}: learners\n({ci}, {n} seeds)")
    b1.legend(fontsize=8)
    x = np.arange(len(rows))
    names = [r["learner"] for r in rows]
    for ax, key, color, label in ((b2, "steps_to_threshold", "tab:green",
                                   f"steps to {thr:.0%} greedy success (budget if never)"),
                                  (b3, "final_anyangle_ratio", "tab:brown",
                                   "driven / any-angle optimum of the disc (successes)")):
        vals = [r[key] or {"mean": np.nan, "ci95": [np.nan, np.nan]} for r in rows]
        m = np.array([v["mean"] for v in vals])
        lo = np.array([v["ci95"][0] for v in vals])
        hi = np.array([v["ci95"][1] for v in vals])
        ax.bar(x, m, yerr=[m - lo, hi - m], capsize=3, color=color)
        ax.set_xticks(x, names, fontsize=8, rotation=30)
        ax.set_ylabel(label)
        ax.set_title(f"sector learners, final checkpoint\n({ci}, {n} seeds)")
    for xi, r in zip(x, rows, strict=True):
        b2.text(xi, r["steps_to_threshold"]["mean"], f"{r['steps_to_threshold']['reached']}/{n}", ha="center",
                va="bottom", fontsize=7)
    finite = [r["final_anyangle_ratio"]["ci95"][0] for r in rows if r["final_anyangle_ratio"]]
    if finite:
        b3.set_ylim(min(1.0, min(finite)) - 0.02, None)  # from 1 (the optimum), not auto-scaled to the noise


def write_study(out: str | Path, data: dict) -> None:
    """study.json (depends only on the seeded jobs: identical on every engine),
    campaign.json (engine, wall and job times, learner and BFS timings), study.png."""
    from firmware_py.atomic import atomic_write

    out = Path(out)
    result = {k: v for k, v in data.items() if k != "campaign"}
    atomic_write(out / "study.json", json.dumps(result, indent=1) + "\n", make_parents=True)
    atomic_write(out / "campaign.json", json.dumps(data["campaign"], indent=1) + "\n")
    atomic_write(out / "study.png", plot_study(data))


def fmt_ci(d: dict | None, scale: float = 1.0, digits: int = 3) -> str:
    if d is None:
        return "-"
    return (f"{d['mean'] * scale:.{digits}f} [{d['ci95'][0] * scale:.{digits}f}, "
            f"{d['ci95'][1] * scale:.{digits}f}]")


def tables(data: dict) -> str:
    """Markdown tables of the study (means with bootstrapped 95 % CIs)."""
    n = data["seeds"]
    thr = f"{data['threshold']:.0%}"
    lines = [f"Learning rate (Q-learning; mean [bootstrapped 95 % CI], {n} seeds; a run that never reaches "
             f"{thr} counts as the {data['config']['steps']:,}-step budget):", "",
             f"| eta | steps to {thr}, epsilon schedule | reached | steps to {thr}, constant epsilon "
             f"{data['constant_epsilon']:g} | reached | final success, schedule | final success, constant |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    rows = {(r["schedule"], r["lr"]): r for r in data["lr_study"]}
    for lr in data["lrs"]:
        d, c = rows[("decay", lr)], rows[("constant", lr)]
        lines.append(f"| {lr:g} | {fmt_ci(d['steps_to_threshold'], 1, 0)} | {d['steps_to_threshold']['reached']}/{n} "
                     f"| {fmt_ci(c['steps_to_threshold'], 1, 0)} | {c['steps_to_threshold']['reached']}/{n} "
                     f"| {fmt_ci(d['final_success'])} | {fmt_ci(c['final_success'])} |")
    wall = data.get("campaign", {}).get("learner_train_seconds", {})
    lines += ["", f"Learners (mean [bootstrapped 95 % CI], {n} seeds, {data['config']['steps']:,} steps, "
              f"epsilon schedule; time = the kernel's, as measured):", "",
              f"| learner | eta | final greedy success | steps to {thr} | reached | path ratio | train ms |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in data["learners"]:
        w = wall.get(f"{r['learner']} lr={r['lr']:g}")
        lines.append(f"| {r['learner']} | {r['lr']:g} | {fmt_ci(r['final_success'])} "
                     f"| {fmt_ci(r['steps_to_threshold'], 1, 0)} | {r['steps_to_threshold']['reached']}/{n} "
                     f"| {fmt_ci(r['final_path_ratio'])} | {fmt_ci(w, 1e3, 1)} |")
    if "sector" in data:
        lines += ["", *sector_table(data)]
    o = data["optimum"]
    t = data.get("campaign", {}).get("optimum")
    lines += ["", f"Optimum: the greedy Q policy (eta {o['config']['lr']:g}, {o['config']['steps']:,} steps, seed "
              f"{o['config']['seed']}) succeeds on {o['success']:.3f} of {o['pairs']} pairs, path ratio mean "
              f"{o['path_ratio_mean']:.3f} (max {o['path_ratio_max']:.3f}) against BFS; BFS is optimal "
              "(ratio 1.0 by definition)."]
    if t:
        lines.append(f"Time: training {t['train_s'] * 1e3:.2f} ms + greedy rollouts {t['greedy_rollouts_s'] * 1e3:.3f} ms;"
                     f" BFS to the training goals {t['bfs_goals_s'] * 1e3:.3f} ms, all pairs of the "
                     f"{t['free_cells']} free cells {t['bfs_all_pairs_s'] * 1e3:.2f} ms (as measured).")
    return "\n".join(lines)


def sector_table(data: dict) -> list[str]:
    """Markdown lines of the sector learner comparison."""
    sec = data["sector"]
    n = sec["seeds"]
    thr = f"{data['threshold']:.0%}"
    wall = data.get("campaign", {}).get("sector_train_seconds", {})
    lines = [f"Learners on the sector encoding ({sec['map']}, shipped sector recipe with {sec['steps']:,} steps, "
             f"guidance {sec['guidance']}; greedy checkpoints every {sec['eval_every']:,} steps on {sec['sample']} "
             f"fixed (start, goal, heading) episodes; mean [bootstrapped 95 % CI], {n} seeds; a run that never "
             f"reaches {thr} counts as the budget; path ratios over successes: driven / octile grid path, and "
             f"driven / (any-angle optimum of the disc robot - goal tolerance); time = training only, as measured):",
             "",
             f"| learner | final greedy success | steps to {thr} | reached | path / octile | path / any-angle "
             "| train s |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in sec["rows"]:
        lines.append(f"| {r['learner']} | {fmt_ci(r['final_success'])} | {fmt_ci(r['steps_to_threshold'], 1, 0)} "
                     f"| {r['steps_to_threshold']['reached']}/{n} | {fmt_ci(r['final_path_ratio'])} "
                     f"| {fmt_ci(r['final_anyangle_ratio'])} | {fmt_ci(wall.get(r['learner']), 1, 2)} |")
    return lines
