"""Tabular training, whatever the kind: read it top to bottom.

1. `TrainConfig`: the common hyperparameters and the kind's own nested in it
   (defined in `ground_station.learn.config` so the CLI parser needs no numba;
   re-exported here); its field help texts become `qnav train --help`.
2. `train(cfg)`: the kind's trainer from the registry (`ground_station.learn.kinds`);
   what the trainers share is here (`TrainResult`, `initial_table`, `run_trainer`).
3. `learning_curve`, `write_run`: the run folder contract
   (`q.npy`, `meta.json`, `metrics.csv`, `learning_curve.png`), written
   atomically.
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from firmware_py.atomic import atomic_write
from ground_station.learn import kinds
from ground_station.learn.config import (  # noqa: F401 - re-exported
    TrainConfig,
    add_config_arguments,
    validate_config,
)
from ground_station.maps import GridMap, load_map


# --- 2. training, by kind ----------------------------------------------------
@dataclass
class TrainResult:
    q: np.ndarray
    returns: np.ndarray  # per finished episode
    successes: np.ndarray  # bool per finished episode
    meta: dict  # encoding-specific meta.json entries
    seconds: float
    q2: np.ndarray | None = None  # Double Q's second table (q is then (A + B) / 2)


def progress_bar(total: int, enabled: bool, desc: str):
    from tqdm import tqdm
    return tqdm(total=total, unit="step", unit_scale=True, disable=not enabled, desc=desc, leave=False)


def initial_table(cfg: TrainConfig, n_states: int, n_actions: int) -> np.ndarray:
    if cfg.q_init_scale > 0:
        rng = np.random.default_rng(cfg.seed)
        return rng.uniform(-cfg.q_init_scale, cfg.q_init_scale, (n_states, n_actions))
    return np.zeros((n_states, n_actions), dtype=np.float64)


def run_in_chunks(run, q: np.ndarray, cfg: TrainConfig, progress: bool,  # type: ignore[no-untyped-def]
                  desc: str) -> tuple[np.ndarray, np.ndarray, float]:
    """`run(q, done, n)` in chunks of `cfg.chunk_steps` (the progress bar's granularity) until
    `cfg.steps`: episode returns, successes, seconds."""
    rets, succs = [], []
    t0 = time.perf_counter()
    done = 0
    with progress_bar(cfg.steps, progress, desc) as bar:
        while done < cfg.steps:
            n = min(cfg.chunk_steps, cfg.steps - done)
            r, s = run(q, done, n)
            rets.append(np.asarray(r, dtype=np.float64))
            succs.append(np.asarray(s, dtype=bool))
            done += n
            bar.update(n)
    return np.concatenate(rets), np.concatenate(succs), time.perf_counter() - t0


def extra_maps(spec: str) -> list[GridMap]:
    """The extra training maps of a comma-separated list of names or generator specs."""
    return [load_map(m.strip()) for m in spec.split(",") if m.strip()]


def run_trainer(make, cfg: TrainConfig, gridmap: GridMap, progress: bool,  # type: ignore[no-untyped-def]
                desc: str):
    """`make(maps)` a trainer on `gridmap` plus the extra maps of `cfg.options.maps`, start its table
    and run it in chunks: (trainer, q, returns, successes, seconds)."""
    trainer = make([gridmap, *extra_maps(cfg.options.maps)])
    q = initial_table(cfg, trainer.n_states, trainer.n_actions)
    rets, succs, seconds = run_in_chunks(trainer.run, q, cfg, progress, f"{desc} {gridmap.name}")
    return trainer, q, rets, succs, seconds


def train(cfg: TrainConfig, gridmap: GridMap | None = None, progress: bool = False) -> TrainResult:
    """Train the configured encoding on `gridmap` (default: load `cfg.map`) with its kind's trainer."""
    validate_config(cfg)
    gm = gridmap if gridmap is not None else load_map(cfg.map)
    result: TrainResult = kinds.resolve(kinds.of_name(cfg.encoding).train)(cfg, gm, progress)
    return result


# --- 3. learning curve and the run folder -------------------------------------
def learning_curve(returns: np.ndarray, successes: np.ndarray, points: int = 200) -> list[dict]:
    """Average return and success rate per window of consecutive episodes."""
    n = len(returns)
    if n == 0:
        return []
    window = max(1, n // points)
    rows = []
    for lo in range(0, n - window + 1, window):
        hi = lo + window
        rows.append({"episode": hi, "avg_return": float(np.mean(returns[lo:hi])),
                     "success_rate": float(np.mean(successes[lo:hi]))})
    return rows


def plot_curve(rows: list[dict], title: str) -> bytes:
    """PNG bytes of the learning curve (average return and success rate)."""
    from ground_station.plotting import png_bytes, pyplot

    plt = pyplot()
    ep = [r["episode"] for r in rows]
    fig, ax1 = plt.subplots(figsize=(7, 4), dpi=100)
    ax1.plot(ep, [r["avg_return"] for r in rows], color="tab:blue", label="average return")
    ax1.set_xlabel("episode")
    ax1.set_ylabel("average return per episode", color="tab:blue")
    ax2 = ax1.twinx()
    ax2.plot(ep, [r["success_rate"] for r in rows], color="tab:green", label="success rate")
    ax2.set_ylabel("success rate", color="tab:green")
    ax2.set_ylim(-0.02, 1.02)
    ax1.set_title(title)
    fig.tight_layout()
    return png_bytes(fig)


def write_run(out: str | Path, cfg: TrainConfig, res: TrainResult) -> dict:
    """Write q.npy, meta.json, metrics.csv, learning_curve.png into `out`."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    # Double Q: q.npy = (A + B) / 2, q_b.npy = B (A = 2 q - B)
    for name, table in (("q.npy", res.q), ("q_b.npy", res.q2)):
        if table is not None:
            buf = io.BytesIO()
            np.save(buf, np.ascontiguousarray(table, dtype=np.float64))
            atomic_write(out / name, buf.getvalue())
    rows = learning_curve(res.returns, res.successes, cfg.curve_points)
    sio = io.StringIO()
    w = csv.DictWriter(sio, fieldnames=["episode", "avg_return", "success_rate"], lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    atomic_write(out / "metrics.csv", sio.getvalue().encode())
    title = f"{cfg.encoding} on {cfg.map}, lr={cfg.lr:g}, seed={cfg.seed}"
    if rows:
        atomic_write(out / "learning_curve.png", plot_curve(rows, title))
    created = datetime.now(UTC)
    from ground_station.learn.robot import trained_for

    meta = {
        "encoding": cfg.encoding,
        **res.meta,
        "robot": trained_for(cfg).to_dict(),  # the robot the twin played (qnav export records its needs)
        "map": cfg.map,
        "config": cfg.flat(),
        "steps": cfg.steps,
        "episodes": int(len(res.returns)),
        "train_seconds": round(res.seconds, 4),
        "steps_per_s": round(cfg.steps / res.seconds) if res.seconds > 0 else None,
        "q_shape": list(res.q.shape),
        "run_name": f"{cfg.map.replace('/', '_')}__{cfg.encoding}__{cfg.seed}__{int(created.timestamp())}",
        "created": created.isoformat(timespec="seconds"),
    }
    atomic_write(out / "meta.json", (json.dumps(meta, indent=1) + "\n").encode())
    return meta
