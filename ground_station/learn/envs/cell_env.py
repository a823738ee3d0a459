"""The `cell` encoding as a Gymnasium environment (the paper's grid world).

Also owns the tables the fast trainer and the evaluator share with it, so the
three cannot drift apart: `resolve_goals`, `cell_transitions`, `reachable_starts`.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from firmware_py import robot_spec
from firmware_py.kinds.cell.encoder import CellEncoder
from ground_station.maps import GridMap, MapError, bfs_distances, load_map

N_ACTIONS = len(robot_spec.CELL_ACTION_DELTAS)


def resolve_goals(gridmap: GridMap, targets: str | list | tuple | None = None,
                  ) -> tuple[list[str], list[tuple[int, int]]]:
    """Goal names and (col, row) cells, in goal-index order, of `targets`: None/"" (all the map's),
    a comma-separated string or a list of names, `col:row` or (col, row). MapError if unusable."""
    if targets is None or targets == "" or targets == []:
        if not gridmap.targets:
            raise MapError(f"map {gridmap.name} defines no targets; pass targets as names or col:row")
        items: list = list(gridmap.targets)
    elif isinstance(targets, str):
        items = [t.strip() for t in targets.split(",") if t.strip()]
    else:
        items = list(targets)
    names: list[str] = []
    goals: list[tuple[int, int]] = []
    for item in items:
        if isinstance(item, tuple | list):
            col, row = int(item[0]), int(item[1])
            name = f"{col}:{row}"
        elif item in gridmap.targets:
            name = item
            col, row = gridmap.targets[item]
        elif isinstance(item, str) and ":" in item:
            try:
                col, row = (int(v) for v in item.split(":"))
            except ValueError:
                raise MapError(f"bad target {item!r}: expected a name or col:row") from None
            name = item
        else:
            known = ", ".join(gridmap.targets) or "none"
            raise MapError(f"map {gridmap.name} has no target {item!r} (targets: {known}; or give col:row)")
        if not gridmap.is_free(col, row):
            raise MapError(f"target {name} at ({col},{row}) is {gridmap.why_not_free(col, row)}")
        if (col, row) in goals:
            raise MapError(f"target {name} at ({col},{row}) given twice")
        names.append(name)
        goals.append((col, row))
    if not goals:
        raise MapError("no targets given")
    return names, goals


def cell_transitions(occ: np.ndarray) -> np.ndarray:
    """int64 (H*W, 4): next cell index (row*W + col) per action, -1 for a collision."""
    h, w = occ.shape
    nxt = np.full((h * w, N_ACTIONS), -1, dtype=np.int64)
    for a, (dc, dr) in enumerate(robot_spec.CELL_ACTION_DELTAS):
        for r in range(h):
            for c in range(w):
                nc, nr = c + dc, r + dr
                if not occ[r, c] and 0 <= nc < w and 0 <= nr < h and not occ[nr, nc]:
                    nxt[r * w + c, a] = nr * w + nc
    return nxt


def goal_distances(gridmap: GridMap, goals: list[tuple[int, int]]) -> np.ndarray:
    """int32 (n_goals, H*W): BFS steps from every cell to each goal, -1 unreachable."""
    return np.stack([bfs_distances(gridmap.occ, c, r).ravel() for c, r in goals])


def reachable_starts(dist: np.ndarray) -> list[np.ndarray]:
    """Per goal, the cell indices that can reach it (the goal itself excluded)."""
    return [np.flatnonzero(d > 0) for d in dist]


class CellNavEnv(gym.Env):
    """Grid navigation to one of several targets (the paper's Figs. 2-4).

    Observation: `Discrete(W*H*n_goals)`, the `CellEncoder` state goal_index*W*H + row*W + col.
    Actions: `Discrete(4)`, `robot_spec.CELL_ACTION_NAMES` up, down, left, right (up = row - 1).
    Rewards: `reward_goal` on entering the goal cell, `reward_collision` on moving into an
    obstacle or off the map (the robot stays), otherwise `reward_step`; both end the episode
    (truncation is a `TimeLimit` wrapper's). Reset: goal uniform over the targets, start uniform
    over the free cells that can reach it; `options={"goal": i, "start": (col, row)}` fixes
    either. Randomness only from `reset(seed=...)`.
    info: `goal_index`, `cell` (col, row), `success`, `collision`.
    """

    metadata = {"render_modes": ["ansi"], "render_fps": 4}

    def __init__(self, gridmap: GridMap | str = "paper10", targets: str | list | None = None,
                 reward_goal: float = 1.0, reward_step: float = -0.01,
                 reward_collision: float = -1.0, render_mode: str | None = None) -> None:
        self.gridmap = load_map(gridmap) if isinstance(gridmap, str) else gridmap
        self.target_names, self.goals = resolve_goals(self.gridmap, targets)
        h, w = self.gridmap.height, self.gridmap.width
        self.encoder = CellEncoder(w, h, len(self.goals))
        self.next_cell = cell_transitions(self.gridmap.occ)
        self.dist = goal_distances(self.gridmap, self.goals)
        self.starts = reachable_starts(self.dist)
        self.goal_cells = np.array([r * w + c for c, r in self.goals], dtype=np.int64)
        self.reward_goal = float(reward_goal)
        self.reward_step = float(reward_step)
        self.reward_collision = float(reward_collision)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"unsupported render_mode {render_mode!r}")
        self.render_mode = render_mode
        self.observation_space = gym.spaces.Discrete(self.encoder.n_states)
        self.action_space = gym.spaces.Discrete(N_ACTIONS)
        self._cell = 0
        self._goal = 0

    def _obs(self) -> int:
        return self._goal * self.gridmap.height * self.gridmap.width + self._cell

    def _info(self, success: bool = False, collision: bool = False) -> dict[str, Any]:
        w = self.gridmap.width
        return {"goal_index": self._goal, "cell": (self._cell % w, self._cell // w),
                "success": success, "collision": collision}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        goal = options.get("goal")
        if goal is None:
            goal = int(self.np_random.integers(len(self.goals)))
        if not 0 <= int(goal) < len(self.goals):
            raise ValueError(f"goal index {goal} outside 0..{len(self.goals) - 1}")
        self._goal = int(goal)
        start = options.get("start")
        if start is None:
            cand = self.starts[self._goal]
            if len(cand) == 0:
                raise MapError(f"no free cell of map {self.gridmap.name} can reach goal {self._goal}")
            self._cell = int(cand[self.np_random.integers(len(cand))])
        else:
            col, row = int(start[0]), int(start[1])
            if not self.gridmap.is_free(col, row):
                raise ValueError(f"start ({col},{row}) is not a free cell")
            self._cell = row * self.gridmap.width + col
        return self._obs(), self._info()

    def step(self, action):
        a = int(action)
        if not 0 <= a < N_ACTIONS:
            raise ValueError(f"action {action} outside 0..{N_ACTIONS - 1}")
        nxt = int(self.next_cell[self._cell, a])
        if nxt < 0:
            return self._obs(), self.reward_collision, True, False, self._info(collision=True)
        self._cell = nxt
        if nxt == self.goal_cells[self._goal]:
            return self._obs(), self.reward_goal, True, False, self._info(success=True)
        return self._obs(), self.reward_step, False, False, self._info()

    def render(self) -> str | None:
        if self.render_mode != "ansi":
            return None
        w = self.gridmap.width
        rows = [["@" if v else "." for v in row] for row in self.gridmap.occ]
        gc, gr = self.goals[self._goal]
        rows[gr][gc] = "G"
        rows[self._cell // w][self._cell % w] = "R"
        return "\n".join("".join(r) for r in rows) + "\n"
