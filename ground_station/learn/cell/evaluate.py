"""The `cell` kind's greedy-policy evaluation against shortest paths, from saved artifacts only.

One greedy rollout from every free start cell to every goal (a seeded sample
of `sample` pairs on large maps). Each rollout ends as

* success: reached the goal; its path ratio = steps / BFS shortest steps,
* collision: the chosen move enters an obstacle or leaves the map,
* loop: the rollout revisits a cell (a deterministic policy then cycles forever),
* timeout: `max_steps` moves without any of the above.

Beside it, the baseline "step to the free neighbour nearest (Euclidean) to the goal".
"""

from __future__ import annotations

import numpy as np

from firmware_py.kinds.cell.encoder import CellEncoder
from ground_station.jitcache import numba
from ground_station.learn.cell.trainer import cell_state
from ground_station.learn.envs.cell_env import cell_transitions, goal_distances, resolve_goals
from ground_station.learn.jit import greedy
from ground_station.maps import GridMap, MapError

SUCCESS, COLLISION, LOOP, TIMEOUT = 0, 1, 2, 3
POLICY_Q, POLICY_NEAREST = 0, 1


@numba.njit(cache=True)
def rollouts_cell(q, next_cell, width, goal_cells, pair_goal, pair_start, max_steps, policy):
    """One deterministic rollout per (goal index, start cell) pair, greedy on q (POLICY_Q) or
    the nearest-neighbour baseline (POLICY_NEAREST): (outcome int8[n], steps int32[n])."""
    n = pair_goal.shape[0]
    n_cells = next_cell.shape[0]
    n_actions = next_cell.shape[1]
    outcome = np.empty(n, dtype=np.int8)
    steps = np.zeros(n, dtype=np.int32)
    stamp = np.full(n_cells, -1, dtype=np.int64)  # rollout id that last visited a cell
    for i in range(n):
        g = pair_goal[i]
        goal = goal_cells[g]
        gc = goal % width
        gr = goal // width
        cell = pair_start[i]
        stamp[cell] = i
        res = TIMEOUT
        for t in range(max_steps):
            if policy == POLICY_Q:
                s = cell_state(g, cell, n_cells)
                a = greedy(q, s)
                nxt = next_cell[cell, a]
            else:
                nxt = -1
                best_d = np.inf
                for k in range(n_actions):
                    c2 = next_cell[cell, k]
                    if c2 >= 0:
                        dc = c2 % width - gc
                        dr = c2 // width - gr
                        d = dc * dc + dr * dr
                        if d < best_d:
                            best_d = d
                            nxt = c2
            steps[i] = t + 1
            if nxt < 0:
                res = COLLISION
                break
            if nxt == goal:
                res = SUCCESS
                break
            if stamp[nxt] == i:
                res = LOOP
                break
            stamp[nxt] = i
            cell = nxt
        outcome[i] = res
    return outcome, steps


def _summary(outcome: np.ndarray, steps: np.ndarray, shortest: np.ndarray) -> dict:
    ok = outcome == SUCCESS
    ratio = steps[ok] / shortest[ok]
    n = len(outcome)
    return {
        "success_rate": float(ok.mean()) if n else 0.0,
        "path_ratio_mean": float(ratio.mean()) if ok.any() else None,
        "path_ratio_max": float(ratio.max()) if ok.any() else None,
        "timeouts": int((outcome == TIMEOUT).sum()),
        "collisions": int((outcome == COLLISION).sum()),
        "loops": int((outcome == LOOP).sum()),
        "episodes": int(n),
    }


def evaluate_cell(q: np.ndarray, gridmap: GridMap, goals: list[tuple[int, int]],
                  sample: int | None = None, seed: int = 0, max_steps: int | None = None,
                  target_names: list[str] | None = None) -> dict:
    """Greedy Q policy vs the nearest-neighbour baseline over all (start, goal) pairs."""
    enc = CellEncoder(gridmap.width, gridmap.height, len(goals))
    if q.shape != (enc.n_states, enc.n_actions):
        raise ValueError(f"Q table shape {q.shape} does not fit a {gridmap.width}x{gridmap.height} map "
                         f"with {len(goals)} goals (expected {(enc.n_states, enc.n_actions)})")
    for c, r in goals:
        if not gridmap.is_free(c, r):
            raise MapError(f"goal ({c},{r}) is {gridmap.why_not_free(c, r)}")
    w = gridmap.width
    dist = goal_distances(gridmap, goals)
    pair_goal, pair_start = np.nonzero(dist > 0)  # every start that can reach the goal, goal excluded
    if sample is not None and len(pair_goal) > sample:
        pick = np.sort(np.random.default_rng(seed).choice(len(pair_goal), sample, replace=False))
        pair_goal, pair_start = pair_goal[pick], pair_start[pick]
    pair_goal = pair_goal.astype(np.int64)
    pair_start = pair_start.astype(np.int64)
    shortest = dist[pair_goal, pair_start].astype(np.float64)
    nxt = cell_transitions(gridmap.occ)
    goal_cells = np.array([r * w + c for c, r in goals], dtype=np.int64)
    limit = int(max_steps or gridmap.width * gridmap.height)
    q64 = np.ascontiguousarray(q, dtype=np.float64)
    out, steps = rollouts_cell(q64, nxt, w, goal_cells, pair_goal, pair_start, limit, POLICY_Q)
    b_out, b_steps = rollouts_cell(q64, nxt, w, goal_cells, pair_goal, pair_start, limit, POLICY_NEAREST)
    rep = _summary(out, steps, shortest)
    base = _summary(b_out, b_steps, shortest)
    rep["baseline_success_rate"] = base["success_rate"]
    rep["baseline"] = base
    names = target_names or [f"{c}:{r}" for c, r in goals]
    rep["per_target"] = {
        name: float((out[pair_goal == g] == SUCCESS).mean()) if (pair_goal == g).any() else None
        for g, name in enumerate(names)}
    rep["encoding"] = "cell"
    rep["map"] = gridmap.name
    return rep


def evaluate_policy(q: np.ndarray, run, gridmap: GridMap, *, sample: int | None = None,  # type: ignore[no-untyped-def]
                    seed: int = 0, full: bool = False) -> dict:
    """The kind's evaluation (`qnav eval`, `qnav export`): `evaluate_cell` of a run's table on
    `gridmap`, which must be the size the table was trained for."""
    enc = run.encoder
    if (enc.width, enc.height) != (gridmap.width, gridmap.height):
        raise ValueError(f"run was trained on a {enc.width}x{enc.height} map, "
                         f"{gridmap.name} is {gridmap.width}x{gridmap.height}")
    names, goals = resolve_goals(gridmap, [list(g) for g in run.goals])
    return evaluate_cell(q, gridmap, goals, sample=sample, seed=seed,
                         target_names=run.meta.get("targets") or names)


def plot_policy(q: np.ndarray, run, gridmap: GridMap) -> bytes:  # type: ignore[no-untyped-def]
    """The kind's plot (`qnav eval --plot`): `plot_cell_policy` of a run's table."""
    return plot_cell_policy(q, gridmap, [tuple(g) for g in run.goals], run.meta.get("targets"))


def greedy_arrows(q: np.ndarray, gridmap: GridMap, goal_index: int, goal: tuple[int, int]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, u, v) of the greedy action's arrow in every free cell but the goal, in the image's
    data coordinates: x = column, y = row, so with row 0 at the top (origin "upper") a move to
    the next row (south) points down (+v)."""
    from firmware_py import robot_spec

    h, w = gridmap.height, gridmap.width
    dc = np.array([d[0] for d in robot_spec.CELL_ACTION_DELTAS], dtype=float)
    dr = np.array([d[1] for d in robot_spec.CELL_ACTION_DELTAS], dtype=float)
    free = np.argwhere(~gridmap.occ)  # (row, col)
    acts = np.argmax(q[goal_index * h * w + free[:, 0] * w + free[:, 1]], axis=1)  # ties -> lowest, as the robot
    keep = ~((free[:, 0] == goal[1]) & (free[:, 1] == goal[0]))
    return free[keep, 1], free[keep, 0], dc[acts[keep]], dr[acts[keep]]


def plot_cell_policy(q: np.ndarray, gridmap: GridMap, goals: list[tuple[int, int]],
                     names: list[str] | None = None) -> bytes:
    """PNG: per goal, the map with the greedy action of every free cell as an
    arrow (north up, row 0 at the top) and the goal marked."""
    from ground_station.plotting import png_bytes, pyplot

    plt = pyplot()
    h, w = gridmap.height, gridmap.width
    names = names or [f"{c}:{r}" for c, r in goals]
    n = len(goals)
    cols = min(n, 4)
    rows = (n + cols - 1) // cols
    size = max(3.0, min(6.0, 40.0 / max(h, w) * 1.0 + 2.5))
    fig, axes = plt.subplots(rows, cols, figsize=(size * cols, size * rows), dpi=100, squeeze=False)
    for g, (gc, gr) in enumerate(goals):
        ax = axes[g // cols][g % cols]
        ax.imshow(gridmap.occ, cmap="Greys", vmin=0, vmax=1.5, origin="upper")
        ax.quiver(*greedy_arrows(q, gridmap, g, (gc, gr)),
                  angles="xy", scale_units="xy", scale=1.5, pivot="middle", color="tab:blue", width=0.006)
        ax.plot([gc], [gr], marker="*", markersize=14, color="tab:red")
        ax.set_title(f"greedy policy to {names[g]} ({gc},{gr})")
        ax.set_xticks([])
        ax.set_yticks([])
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].axis("off")
    fig.tight_layout()
    return png_bytes(fig)
