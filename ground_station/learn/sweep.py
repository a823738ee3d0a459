"""Learning-rate study (the paper's Fig. 5): train every (eta, seed) pair on
both cores, evaluate each greedy policy, write a figure and JSON.

Each job is independent and seeded, so the result does not depend on how
jobs are spread over processes.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
from dataclasses import asdict, replace
from pathlib import Path

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
    from ground_station.learn.evaluate import evaluate_cell
    from ground_station.learn.train import learning_curve, train
    from ground_station.maps import load_map

    cfg = TrainConfig(**cfg_dict)
    gm = load_map(cfg.map)
    res = train(cfg, gm)
    if cfg.encoding == "cell":
        goals = [tuple(g) for g in res.meta["goals"]]
        ev = evaluate_cell(res.q, gm, goals, sample=20_000, seed=cfg.seed)
    else:
        from ground_station.learn.evaluate import sector_encoder_from_meta
        from ground_station.learn.sector.evaluate import evaluate_sector
        ev = evaluate_sector(res.q, gm, sector_encoder_from_meta(res.meta["encoder"]), seed=cfg.seed)
    curve = learning_curve(res.returns, res.successes, cfg.curve_points)
    return {"lr": cfg.lr, "seed": cfg.seed, "train_seconds": res.seconds, "episodes": int(len(res.returns)),
            "success_rate": ev["success_rate"], "path_ratio_mean": ev["path_ratio_mean"],
            "loops": ev["loops"], "collisions": ev["collisions"], "timeouts": ev["timeouts"],
            "q_max_mean": float(res.q.max(axis=1).mean()), "curve": curve}


def sweep(base: TrainConfig, lrs: list[float], seeds: int, processes: int | None = None,
          progress: bool = False) -> dict:
    """Run every (lr, seed) job on `processes` workers (default: all cores)."""
    from tqdm import tqdm

    jobs = [asdict(replace(base, lr=lr, seed=base.seed + k)) for lr in lrs for k in range(seeds)]
    procs = processes or os.cpu_count() or 1
    results: list[dict] = []
    with tqdm(total=len(jobs), unit="run", disable=not progress, desc="sweep", leave=False) as bar:
        if procs == 1:
            for j in jobs:
                results.append(run_job(j))
                bar.update(1)
        else:
            with mp.get_context("fork").Pool(min(procs, len(jobs))) as pool:
                for r in pool.imap_unordered(run_job, jobs):
                    results.append(r)
                    bar.update(1)
    results.sort(key=lambda r: (r["lr"], r["seed"]))
    summary = []
    for lr in lrs:
        rs = [r for r in results if r["lr"] == lr]
        succ = np.array([r["success_rate"] for r in rs])
        final_ret = np.array([r["curve"][-1]["avg_return"] if r["curve"] else np.nan for r in rs])
        n = min(len(r["curve"]) for r in rs)
        curve = [{"episode": float(np.mean([r["curve"][i]["episode"] for r in rs])),
                  "avg_return": float(np.mean([r["curve"][i]["avg_return"] for r in rs])),
                  "success_rate": float(np.mean([r["curve"][i]["success_rate"] for r in rs]))}
                 for i in range(n)]
        summary.append({"lr": lr, "success_mean": float(succ.mean()), "success_std": float(succ.std()),
                        "final_avg_return_mean": float(np.nanmean(final_ret)),
                        "final_avg_return_std": float(np.nanstd(final_ret)),
                        "path_ratio_mean": float(np.mean([r["path_ratio_mean"] for r in rs
                                                          if r["path_ratio_mean"] is not None] or [np.nan])),
                        "q_max_mean": float(np.mean([r["q_max_mean"] for r in rs])),
                        "curve": curve})
    for r in results:
        del r["curve"]
    return {"map": base.map, "encoding": base.encoding, "lrs": lrs, "seeds": seeds,
            "processes": procs, "config": asdict(base), "summary": summary, "runs": results}


def plot_sweep(data: dict) -> bytes:
    """PNG: learning curves per eta (mean over seeds); greedy success and
    final training return vs eta; path ratio vs eta."""
    from ground_station.plotting import png_bytes, pyplot

    plt = pyplot()
    fig, (ax1, ax2, ax4) = plt.subplots(1, 3, figsize=(16, 4.5), dpi=100)
    cmap = plt.get_cmap("viridis")
    lrs = data["lrs"]
    for i, s in enumerate(data["summary"]):
        ax1.plot([p["episode"] for p in s["curve"]], [p["avg_return"] for p in s["curve"]],
                 color=cmap(i / max(1, len(lrs) - 1)), label=f"eta={s['lr']:g}")
    ax1.set_xlabel("episode")
    ax1.set_ylabel("average return per episode (mean over seeds)")
    ax1.set_title(f"learning curves, {data['encoding']} on {data['map']}")
    ax1.legend(fontsize=7, ncol=2)
    sm = data["summary"]
    ax2.errorbar(lrs, [s["success_mean"] for s in sm], yerr=[s["success_std"] for s in sm],
                 marker="o", color="tab:green", capsize=3, label="greedy success rate")
    ax2.set_xlabel("learning rate eta")
    ax2.set_ylabel("greedy success rate", color="tab:green")
    ax2.set_ylim(-0.02, 1.05)
    ax3 = ax2.twinx()
    ax3.errorbar(lrs, [s["final_avg_return_mean"] for s in sm], yerr=[s["final_avg_return_std"] for s in sm],
                 marker="s", color="tab:blue", capsize=3, label="final average return")
    ax3.set_ylabel("final average return (training)", color="tab:blue")
    ax2.set_title(f"learning-rate study, {data['seeds']} seeds each")
    ax4.plot(lrs, [s["path_ratio_mean"] for s in sm], marker="o", color="tab:red")
    ax4.set_xlabel("learning rate eta")
    ax4.set_ylabel("greedy path length / shortest (mean)")
    ax4.set_title("path quality of successful rollouts")
    fig.tight_layout()
    return png_bytes(fig)


def write_sweep(out: str | Path, data: dict) -> None:
    from firmware_py.atomic import atomic_write

    out = Path(out)
    atomic_write(out / "sweep.json", json.dumps(data, indent=1) + "\n", make_parents=True)
    atomic_write(out / "sweep.png", plot_sweep(data))
