"""Tabular Q-learning trainer, CleanRL style: read it top to bottom.

1. `TrainConfig`: every hyperparameter in one dataclass (defined in
   `ground_station.learn.config` so the CLI parser needs no numba; re-exported
   here); its field help texts become `qnav train --help`.
2. The numba kernel: exact sequential Q-learning on the `cell` encoding
   (one environment, one update per step, in order), the update

       Q(s, a) <- Q(s, a) + eta * (r + gamma * max_a' Q(s', a') - Q(s, a))

   with no bootstrap on termination (goal or collision) and bootstrap on
   truncation (episode step limit), epsilon-greedy actions (greedy ties
   -> lowest action index, as on the robot), a linear epsilon schedule, and a
   random goal and start at every episode (the paper's training protocol).
   Its random numbers come from its own xorshift64* state, so a seed fixes
   the table regardless of chunking or process.
3. `train_cell` / `train_sector`: run the kernel (or the sector encoding's
   `SectorTrainer`, `ground_station.learn.sector.trainer`) in chunks under a
   tqdm progress bar.
4. `learning_curve`, `write_run`: the run folder contract
   (`q.npy`, `meta.json`, `metrics.csv`, `learning_curve.png`), written
   atomically.

The `cell` kernel's transitions come from `ground_station.learn.envs.cell_env`, the
same tables the Gymnasium `CellNavEnv` steps through.
"""

from __future__ import annotations

import csv
import io
import json
import time
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path

import numba
import numpy as np

from firmware_py.atomic import atomic_write
from firmware_py.encoders import CellEncoder
from ground_station.learn.config import (  # noqa: F401 - re-exported
    TrainConfig,
    add_config_arguments,
    config_from_args,
    validate_config,
)
from ground_station.learn.envs.cell_env import (
    cell_transitions,
    goal_distances,
    reachable_starts,
    resolve_goals,
)
from ground_station.learn.jit import (
    cell_step,
    draw_episode_start,
    epsilon_at,
    greedy,
    rand01,
    seed_state,
)
from ground_station.maps import GridMap, MapError, load_map

# --------------------------------------------------------------------------
# 1. configuration (ground_station/learn/config.py, imported without numba)
# --------------------------------------------------------------------------
# TrainConfig: map, encoding, targets, seed, steps, lr (eta), gamma,
# epsilon_start/end/decay (linear schedule), max_episode_steps, rewards
# (goal, step, collision), the sector_* fields (encoder, guidance, reward
# shaping, action hold, lr decay, range noise, extra maps), q_init_scale,
# curve_points, chunk_steps. meta.json records every field.


# --------------------------------------------------------------------------
# 2. the numba kernel
# --------------------------------------------------------------------------
@numba.njit(cache=True, inline="always")
def cell_state(goal_index, cell, n_cells):
    """Jitted copy of `CellEncoder.encode` (cell = row * W + col); a test
    checks it against the reference on random inputs."""
    return goal_index * n_cells + cell


@numba.njit(cache=True, inline="always")
def q_update(q, s, a, r, s2, terminal, lr, gamma):
    """The paper's update: Q(s,a) += lr * (r + gamma * max Q(s2, .) - Q(s,a));
    no bootstrap when `terminal` (goal or collision)."""
    target = r
    if not terminal:
        m = q[s2, 0]
        for k in range(1, q.shape[1]):
            if q[s2, k] > m:
                m = q[s2, k]
        target += gamma * m
    q[s, a] += lr * (target - q[s, a])


@numba.njit(cache=True)
def q_learning_cell(q, next_cell, goal_cells, starts_flat, starts_off,
                    lr, gamma, eps_start, eps_end, eps_decay_steps,
                    r_goal, r_step, r_coll, max_ep_steps,
                    start_step, n_steps, rng, ep, ep_ret, out_ret, out_succ):
    """Advance training by `n_steps` steps from global step `start_step`.

    q: float64 (n_goals*H*W, 4), updated in place. next_cell: (H*W, 4) from
    `cell_transitions`. starts_flat[starts_off[g]:starts_off[g+1]] are goal
    g's start cells. ep = [cell, goal, steps in episode, active] and
    ep_ret = [return so far] carry an unfinished episode across calls.
    Finished episodes' returns/successes go to out_ret/out_succ; returns
    how many finished."""
    n_goals = goal_cells.shape[0]
    n_cells = next_cell.shape[0]
    n_actions = q.shape[1]
    cell = ep[0]
    g = ep[1]
    t_ep = ep[2]
    active = ep[3]
    ret = ep_ret[0]
    n_done = 0
    for i in range(n_steps):
        if active == 0:
            g, cell = draw_episode_start(rng, n_goals, starts_flat, starts_off)
            t_ep = 0
            ret = 0.0
            active = 1
        t = start_step + i
        eps = epsilon_at(t, eps_start, eps_end, eps_decay_steps)
        s = cell_state(g, cell, n_cells)
        if rand01(rng) < eps:
            a = int(rand01(rng) * n_actions)
        else:
            a = greedy(q, s)
        c2 = next_cell[cell, a]
        t_ep += 1
        c2, r, done, success = cell_step(cell, c2, goal_cells[g], r_goal, r_step, r_coll)
        q_update(q, s, a, r, cell_state(g, c2, n_cells), done, lr, gamma)
        cell = c2
        ret += r
        if done or t_ep >= max_ep_steps:
            out_ret[n_done] = ret
            out_succ[n_done] = success
            n_done += 1
            active = 0
    ep[0] = cell
    ep[1] = g
    ep[2] = t_ep
    ep[3] = active
    ep_ret[0] = ret
    return n_done


# --------------------------------------------------------------------------
# 3. training loops
# --------------------------------------------------------------------------
@dataclass
class TrainResult:
    q: np.ndarray
    returns: np.ndarray  # per finished episode
    successes: np.ndarray  # bool per finished episode
    meta: dict  # encoding-specific meta.json entries
    seconds: float
    q2: np.ndarray | None = None  # Double Q's second table (q is then (A + B) / 2)


@dataclass
class CellProblem:
    """Everything the cell kernel needs, derived from a map and its goals."""

    gridmap: GridMap
    target_names: list[str]
    goals: list[tuple[int, int]]
    encoder: CellEncoder
    next_cell: np.ndarray
    goal_cells: np.ndarray
    starts_flat: np.ndarray
    starts_off: np.ndarray
    dist: np.ndarray

    @classmethod
    def build(cls, gridmap: GridMap, targets: str | list | None = None) -> CellProblem:
        names, goals = resolve_goals(gridmap, targets)
        dist = goal_distances(gridmap, goals)
        starts = reachable_starts(dist)
        for name, s in zip(names, starts, strict=True):
            if len(s) == 0:
                raise MapError(f"target {name} of map {gridmap.name} cannot be reached from any free cell")
        off = np.zeros(len(starts) + 1, dtype=np.int64)
        off[1:] = np.cumsum([len(s) for s in starts])
        w = gridmap.width
        return cls(gridmap, names, goals, CellEncoder(w, gridmap.height, len(goals)),
                   cell_transitions(gridmap.occ),
                   np.array([r * w + c for c, r in goals], dtype=np.int64),
                   np.concatenate(starts).astype(np.int64), off, dist)


def _progress(total: int, enabled: bool, desc: str):
    from tqdm import tqdm
    return tqdm(total=total, unit="step", unit_scale=True, disable=not enabled, desc=desc, leave=False)


def initial_table(cfg: TrainConfig, n_states: int, n_actions: int) -> np.ndarray:
    if cfg.q_init_scale > 0:
        rng = np.random.default_rng(cfg.seed)
        return rng.uniform(-cfg.q_init_scale, cfg.q_init_scale, (n_states, n_actions))
    return np.zeros((n_states, n_actions), dtype=np.float64)


def train_cell(cfg: TrainConfig, gridmap: GridMap, progress: bool = False) -> TrainResult:
    """Exact sequential Q-learning on the cell encoding (other learners:
    `ground_station.learn.cell.learners`, same problem, schedule and rewards)."""
    prob = CellProblem.build(gridmap, cfg.targets or None)
    q = initial_table(cfg, prob.encoder.n_states, prob.encoder.n_actions)
    meta = {"encoder": prob.encoder.to_dict(), "targets": prob.target_names,
            "goals": [list(g) for g in prob.goals], "learner": cfg.learner}
    if cfg.learner != "q":
        from ground_station.learn.cell.learners import train_cell_learner

        with _progress(cfg.steps, progress, f"train cell {cfg.learner} {gridmap.name}") as bar:
            table, q2, rets_a, succs_a, secs = train_cell_learner(cfg, prob, q, bar)
        return TrainResult(table, rets_a, succs_a, meta, secs, q2)
    max_ep = cfg.max_episode_steps or gridmap.width * gridmap.height
    rng = seed_state(cfg.seed)
    ep = np.zeros(4, dtype=np.int64)
    ep_ret = np.zeros(1, dtype=np.float64)
    decay = int(cfg.epsilon_decay * cfg.steps)
    chunk = min(cfg.chunk_steps, cfg.steps)
    out_ret = np.empty(chunk, dtype=np.float64)
    out_succ = np.empty(chunk, dtype=np.bool_)
    rets, succs = [], []
    t0 = time.perf_counter()
    done = 0
    with _progress(cfg.steps, progress, f"train cell {gridmap.name}") as bar:
        while done < cfg.steps:
            n = min(chunk, cfg.steps - done)
            k = q_learning_cell(q, prob.next_cell, prob.goal_cells, prob.starts_flat, prob.starts_off,
                                cfg.lr, cfg.gamma, cfg.epsilon_start, cfg.epsilon_end, decay,
                                cfg.reward_goal, cfg.reward_step, cfg.reward_collision, max_ep,
                                done, n, rng, ep, ep_ret, out_ret, out_succ)
            rets.append(out_ret[:k].copy())
            succs.append(out_succ[:k].copy())
            done += n
            bar.update(n)
    seconds = time.perf_counter() - t0
    return TrainResult(q, np.concatenate(rets), np.concatenate(succs), meta, seconds)


def _run_in_chunks(trainer, q: np.ndarray, cfg: TrainConfig, progress: bool,
                   desc: str) -> tuple[np.ndarray, np.ndarray, float]:
    """`trainer.run(q, done, n)` in chunks of `cfg.chunk_steps` (the progress
    bar's granularity) until `cfg.steps`: episode returns, successes, seconds."""
    rets, succs = [], []
    t0 = time.perf_counter()
    done = 0
    with _progress(cfg.steps, progress, desc) as bar:
        while done < cfg.steps:
            n = min(cfg.chunk_steps, cfg.steps - done)
            r, s = trainer.run(q, done, n)
            rets.append(np.asarray(r, dtype=np.float64))
            succs.append(np.asarray(s, dtype=bool))
            done += n
            bar.update(n)
    return np.concatenate(rets), np.concatenate(succs), time.perf_counter() - t0


def train_sector(cfg: TrainConfig, gridmap: GridMap, progress: bool = False) -> TrainResult:
    """Q-learning on the sector twin, through `ground_station.learn.sector.trainer.SectorTrainer`,
    on `gridmap` plus the `sector_maps` extras."""
    from ground_station.learn.sector.trainer import SectorTrainer, sector_encoder

    encoder = sector_encoder(cfg)
    extra = [load_map(m.strip()) for m in cfg.sector_maps.split(",") if m.strip()]
    trainer = SectorTrainer([gridmap, *extra], cfg, encoder)
    q = initial_table(cfg, trainer.n_states, trainer.n_actions)
    rets, succs, seconds = _run_in_chunks(trainer, q, cfg, progress, f"train sector {gridmap.name}")
    q, q2 = trainer.table(q), trainer.q2  # Double Q: (A + B) / 2 and B
    return TrainResult(q, rets, succs,
                       {"encoder": encoder.to_dict(), "guidance": trainer.guidance,
                        "margin_mm": cfg.sector_margin_mm, "max_segment_mm": cfg.sector_max_segment_mm,
                        "train_maps": [m.name for m in trainer.maps]}, seconds, q2)


def train_sector_memory_grid(cfg: TrainConfig, gridmap: GridMap, progress: bool = False) -> TrainResult:
    """Q-learning of the cell-stepped sector-memory encoding (direct setting)
    on the grid twin, through `ground_station.learn.sector_memory.trainer.GridBugTrainer`,
    on `gridmap` plus the `sector_maps` extras."""
    from ground_station.learn.sector_memory.trainer import GridBugTrainer, gridbug_encoder

    encoder = gridbug_encoder(cfg)
    extra = [load_map(m.strip()) for m in cfg.sector_maps.split(",") if m.strip()]
    trainer = GridBugTrainer([gridmap, *extra], cfg, encoder)
    q = initial_table(cfg, trainer.n_states, trainer.n_actions)
    rets, succs, seconds = _run_in_chunks(trainer, q, cfg, progress, f"train sector-memory {gridmap.name}")
    return TrainResult(q, rets, succs,
                       {"encoder": encoder.to_dict(), "guidance": "direct",
                        "train_maps": [m.name for m in trainer.maps]}, seconds)


def train(cfg: TrainConfig, gridmap: GridMap | None = None, progress: bool = False) -> TrainResult:
    """Train the configured encoding on `gridmap` (default: load `cfg.map`)."""
    validate_config(cfg)
    gm = gridmap if gridmap is not None else load_map(cfg.map)
    if cfg.encoding == "cell":
        return train_cell(cfg, gm, progress)
    if cfg.encoding == "sector-memory":
        return train_sector_memory_grid(cfg, gm, progress)
    return train_sector(cfg, gm, progress)


# --------------------------------------------------------------------------
# 4. learning curve and the run folder
# --------------------------------------------------------------------------
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
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(res.q, dtype=np.float64))
    atomic_write(out / "q.npy", buf.getvalue())
    if res.q2 is not None:  # Double Q: q.npy = (A + B) / 2, q_b.npy = B (A = 2 q - B)
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(res.q2, dtype=np.float64))
        atomic_write(out / "q_b.npy", buf.getvalue())
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
    meta = {
        "encoding": cfg.encoding,
        **res.meta,
        "map": cfg.map,
        "config": asdict(cfg),
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
