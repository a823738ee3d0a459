"""Learning-rate study (the paper's Fig. 5): train every (eta, seed) pair on
both cores, evaluate each greedy policy, write a figure and JSON.

Each job is independent and seeded, so the result does not depend on how
jobs are spread over processes.
"""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from ground_station.learn.config import TrainConfig


def parse_lrs(spec: str) -> list[float]:
    """`start:stop:step` (inclusive) or a comma list -> learning rates."""
    spec = spec.strip()
    try:
        if ":" in spec:
            start, stop, step = (float(v) for v in spec.split(":"))
            if step <= 0 or stop < start:
                raise ValueError
            n = int(np.floor((stop - start) / step + 1e-9)) + 1
            lrs = [round(start + i * step, 10) for i in range(n)]
        else:
            lrs = [float(v) for v in spec.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"bad learning-rate list {spec!r}: use start:stop:step or a,b,c") from None
    if not lrs or any(not 0 < v <= 1 for v in lrs):
        raise ValueError(f"learning rates must be in (0, 1], got {spec!r}")
    return lrs


def run_job(cfg_dict: dict) -> dict:
    """Train one config and evaluate its greedy policy on the same map."""
    from ground_station.learn import kinds
    from ground_station.learn.evaluate import evaluate_table
    from ground_station.learn.export import run_of
    from ground_station.learn.train import learning_curve, train
    from ground_station.maps import load_map

    cfg = TrainConfig.of(**cfg_dict)
    gm = load_map(cfg.map)
    res = train(cfg, gm)
    ev = evaluate_table(res.q, run_of(res.q, {"encoding": cfg.encoding, **res.meta}), gm,
                        sample=kinds.of_name(cfg.encoding).sweep_sample, seed=cfg.seed)
    curve = learning_curve(res.returns, res.successes, cfg.curve_points)
    return {"lr": cfg.lr, "seed": cfg.seed, "train_seconds": res.seconds, "episodes": int(len(res.returns)),
            "success_rate": ev["success_rate"], "path_ratio_mean": ev["path_ratio_mean"],
            "loops": ev.get("loops", 0), "collisions": ev["collisions"], "timeouts": ev["timeouts"],
            "q_max_mean": float(res.q.max(axis=1).mean()), "curve": curve}


def with_values(cfg: TrainConfig, **flat: Any) -> TrainConfig:
    """A copy of `cfg` with some flat-named values changed (an encoding change starts from its defaults)."""
    if "encoding" in flat and flat["encoding"] != cfg.encoding:
        return TrainConfig.of(**{**{f.name: getattr(cfg, f.name) for f in fields(cfg) if f.name != "options"},
                                 **flat})
    return TrainConfig.of(**{**cfg.flat(), **flat})


def sweep_jobs(base: TrainConfig, lrs: list[float], seeds: int,
               points: list[dict] | None = None) -> list[dict]:
    """The campaign's job list: every search point x learning rate x seed,
    each a full TrainConfig dict (seeds base.seed .. base.seed + seeds - 1)."""
    return [with_values(base, **point, lr=lr, seed=base.seed + k).flat()
            for point in (points or [{}]) for lr in lrs for k in range(seeds)]


def sweep(base: TrainConfig, lrs: list[float], seeds: int, engine=None, progress: bool = False,
          points: list[dict] | None = None, tune_dir: Path | None = None) -> dict:
    """Run every (point, lr, seed) job on `engine` (default: the local pool on
    all cores), or as Ray Tune trials stored in `tune_dir` when given
    (resumable). The result depends only on the jobs; where and how long they
    ran is in `data["campaign"]`, which `write_sweep` keeps apart."""
    from ground_station.lab.campaign.engines import LocalEngine

    jobs = sweep_jobs(base, lrs, seeds, points)
    if tune_dir is not None:
        from ground_station.lab.campaign.tune import run_on_tune

        results, stats = run_on_tune(run_job, jobs, tune_dir, engine, progress=progress)
    else:
        engine = engine or LocalEngine()
        results, stats = engine.map(run_job, jobs, desc="sweep", progress=progress, unit="run")
    seconds = [r.pop("train_seconds") for r in results]
    for r, job in zip(results, jobs, strict=True):
        r["point"] = {k: job[k] for k in (points or [{}])[0]}
    campaign = {**stats.as_dict(), "tune_dir": str(tune_dir) if tune_dir else None,
                "train_seconds_total": round(sum(seconds), 3)}
    summary = []
    for point, lr in [(p, lr) for p in (points or [{}]) for lr in lrs]:
        rs = [r for r in results if r["lr"] == lr and r["point"] == point]
        succ = np.array([r["success_rate"] for r in rs])
        final_ret = np.array([r["curve"][-1]["avg_return"] if r["curve"] else np.nan for r in rs])
        n = min(len(r["curve"]) for r in rs)
        curve = [{"episode": float(np.mean([r["curve"][i]["episode"] for r in rs])),
                  "avg_return": float(np.mean([r["curve"][i]["avg_return"] for r in rs])),
                  "success_rate": float(np.mean([r["curve"][i]["success_rate"] for r in rs]))}
                 for i in range(n)]
        ratios = [r["path_ratio_mean"] for r in rs if r["path_ratio_mean"] is not None]
        summary.append({"point": point, "lr": lr, "success_mean": float(succ.mean()), "success_std": float(succ.std()),
                        "success_ci95": _ci95(succ), "final_avg_return_ci95": _ci95(final_ret[~np.isnan(final_ret)]),
                        "path_ratio_ci95": _ci95(np.array(ratios)),
                        "final_avg_return_mean": float(np.nanmean(final_ret)),
                        "final_avg_return_std": float(np.nanstd(final_ret)),
                        "path_ratio_mean": float(np.mean([r["path_ratio_mean"] for r in rs
                                                          if r["path_ratio_mean"] is not None] or [np.nan])),
                        "q_max_mean": float(np.mean([r["q_max_mean"] for r in rs])),
                        "curve": curve})
    for r in results:
        del r["curve"]
    return {"map": base.map, "encoding": base.encoding, "lrs": lrs, "seeds": seeds,
            "points": points or [{}], "config": base.flat(), "summary": summary, "runs": results,
            "campaign": campaign}


def _ci95(values: np.ndarray) -> list[float] | None:
    """Bootstrapped 95 % CI of the mean over seeds (`ground_station.lab.study.bootstrap_ci`)."""
    from ground_station.lab.study import bootstrap_ci

    if len(values) == 0:
        return None
    _, lo, hi = bootstrap_ci(values)
    return [float(lo), float(hi)]


def _yerr(sm: list[dict], mean: str, ci: str) -> list[list[float]]:
    """errorbar's (below, above) from the summaries' CIs (0 where a CI is missing)."""
    lo = [s[mean] - s[ci][0] if s.get(ci) else 0.0 for s in sm]
    hi = [s[ci][1] - s[mean] if s.get(ci) else 0.0 for s in sm]
    return [lo, hi]


def plot_sweep(data: dict) -> bytes:
    """PNG: learning curves per eta (mean over seeds); greedy success and
    final training return vs eta; path ratio vs eta."""
    from ground_station.plotting import png_bytes, pyplot

    plt = pyplot()
    fig, (ax1, ax2, ax4) = plt.subplots(1, 3, figsize=(16, 4.5), dpi=100)
    cmap = plt.get_cmap("viridis")
    from ground_station.lab.campaign.space import label

    lrs = data["lrs"]
    n_curves = max(1, len(data["summary"]) - 1)
    for i, s in enumerate(data["summary"]):
        name = f"eta={s['lr']:g}" + (f", {label(s['point'])}" if s.get("point") else "")
        ax1.plot([p["episode"] for p in s["curve"]], [p["avg_return"] for p in s["curve"]],
                 color=cmap(i / n_curves), label=name)
    ax1.set_xlabel("episode")
    ax1.set_ylabel("average return per episode (mean over seeds)")
    ax1.set_title(f"learning curves, {data['encoding']} on {data['map']}")
    ax1.legend(fontsize=7, ncol=2)
    ax3 = ax2.twinx()
    series = data.get("points") or [{}]
    for point in series:
        sm = [s for s in data["summary"] if s.get("point", {}) == point]
        suffix = f" ({label(point)})" if point else ""
        ax2.errorbar(lrs, [s["success_mean"] for s in sm], yerr=_yerr(sm, "success_mean", "success_ci95"),
                     marker="o", capsize=3, label="greedy success rate" + suffix,
                     color="tab:green" if len(series) == 1 else None)
        ax3.errorbar(lrs, [s["final_avg_return_mean"] for s in sm],
                     yerr=_yerr(sm, "final_avg_return_mean", "final_avg_return_ci95"),
                     marker="s", capsize=3, linestyle="--", label="final average return" + suffix,
                     color="tab:blue" if len(series) == 1 else None)
        ax4.errorbar(lrs, [s["path_ratio_mean"] for s in sm], yerr=_yerr(sm, "path_ratio_mean", "path_ratio_ci95"),
                     marker="o", capsize=3, label=label(point), color="tab:red" if len(series) == 1 else None)
    ax2.set_xlabel("learning rate eta")
    ax2.set_ylabel("greedy success rate (solid)", color="tab:green")
    ax2.set_ylim(-0.02, 1.05)
    ax3.set_ylabel("final average return, training (dashed)", color="tab:blue")
    ax2.set_title(f"learning-rate study: mean, bootstrapped 95 % CI, {data['seeds']} seeds")
    if len(series) > 1:
        ax4.legend(fontsize=7)
    ax4.set_xlabel("learning rate eta")
    ax4.set_ylabel("greedy path length / shortest (mean over successful rollouts)")
    # a fixed scale from the optimum (1.0): an auto-scaled axis made 0.1 % look like a trend
    ratios = [v for s in data["summary"] for v in (s.get("path_ratio_ci95") or [s["path_ratio_mean"]])
              if v is not None and np.isfinite(v)]
    top = max([1.1, *ratios]) if ratios else 1.1
    ax4.set_ylim(min([1.0, *ratios]) - 0.02 if ratios else 0.9, top + 0.02)
    ax4.set_title(f"path quality of successful rollouts\n(mean, bootstrapped 95 % CI, {data['seeds']} seeds)")
    fig.tight_layout()
    return png_bytes(fig)


def write_sweep(out: str | Path, data: dict) -> None:
    """sweep.json (depends only on the seeded jobs: identical on every engine),
    campaign.json (engine, workers, nodes, wall time) and sweep.png."""
    from firmware_py.atomic import atomic_write

    out = Path(out)
    result = {k: v for k, v in data.items() if k != "campaign"}
    atomic_write(out / "sweep.json", json.dumps(result, indent=1) + "\n", make_parents=True)
    if "campaign" in data:
        atomic_write(out / "campaign.json", json.dumps(data["campaign"], indent=1) + "\n")
    atomic_write(out / "sweep.png", plot_sweep(data))
