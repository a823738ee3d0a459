"""The `sector` encoding as a Gymnasium environment on the kinematic twin.

Physics, sensing and reward are the jitted functions the fast trainer uses
(`ground_station.learn.sector.twin`, `ground_station.learn.sector.kernels.period_step`
with the weights of `ground_station.learn.sector.reward.SectorReward`), so the
env and the trainer cannot drift apart.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np

from firmware_py import robot_spec
from firmware_py.kinds.sector.encoder import SectorEncoder
from ground_station.learn.config import TrainConfig
from ground_station.learn.sector.kernels import guide_potential, period_step, start_guidance
from ground_station.learn.sector.reward import SectorReward, check_guidance
from ground_station.learn.sector.twin import (
    TwinRobot,
    bearing_mrad,
    cell_centre,
    encode_fast,
    encoder_arrays,
    grid_of,
    sense,
)
from ground_station.maps import GridMap, MapError, load_map, octile_distances
from ground_station.maps.planner import DEFAULT_MARGIN_MM, DEFAULT_MAX_SEGMENT_MM, clearance_mm


class SectorNavEnv(gym.Env):
    """Drive the robot's kinematic twin to a goal cell on a grid map.

    The robot (`robot`, a `TwinRobot`; default the built-in one) is a disc of its body radius
    with continuous pose (x, y mm; heading rad, CCW from east); the map border is a wall.

    * Action space: `Discrete(4)` = `robot_spec.ACTION_NAMES`, each action's wheel speeds held
      for one control period.
    * Guidance (`guidance`): "path" (default) = the planner's waypoints from the start pose,
      each passed within `robot_spec.GOAL_TOLERANCE_MM` as the controller runs a mission;
      "direct" = the goal alone.
    * Observation space: `Discrete(encoder.n_states)`, the reference `SectorEncoder`'s state
      of the simulated range readings, exactly as the robot computes it from its CAN frames.
    * Reward per period: `SectorReward`'s (default: the `TrainConfig` defaults), as defined
      in `ground_station.learn.sector.kernels`.
    * Episode end: terminated on reaching the goal cell's centre (within
      GOAL_TOLERANCE_MM) or a collision; truncation is the TimeLimit wrapper's.
    * Reset: goal = `goal` (target name or (col, row)), else a random free cell; start = a
      random other connected free cell, uniform within +-(cell/2 - radius) of its centre,
      heading uniform; `options` may fix `start` (col, row; at the centre), `heading`, `goal`.
    * Info: pose, goal, `waypoints`, `waypoint`, the encoder's sensors' ranges/status,
      `success`, `collision`, `driven_mm`.
    """

    metadata = {"render_modes": []}

    def __init__(self, gridmap: GridMap | str = "paper10", encoder: SectorEncoder | None = None,
                 goal: str | tuple[int, int] | None = None, reward: SectorReward | None = None,
                 guidance: str = "path", margin_mm: float = DEFAULT_MARGIN_MM,
                 max_segment_mm: float = DEFAULT_MAX_SEGMENT_MM, robot: TwinRobot | None = None) -> None:
        self.robot = robot or TwinRobot()  # the robot profile's twin (default the built-in robot)
        self._tw = self.robot.arrays()
        self.gridmap = load_map(gridmap) if isinstance(gridmap, str) else gridmap
        self.encoder = encoder or SectorEncoder()
        self.reward = reward or SectorReward.from_config(TrainConfig.of(encoding="sector"))
        self._rw = self.reward.array()
        self.guidance = guidance
        self._guided = check_guidance(guidance)
        self._clear_r = clearance_mm(margin_mm, self.robot.radius_mm)
        self._max_seg = float(max_segment_mm)
        self._occ, self._h, self._w, self._c = grid_of(self.gridmap)
        self._enc = encoder_arrays(self.encoder)
        self._free = self.gridmap.free_cells()
        if len(self._free) < 2:
            raise MapError(f"map {self.gridmap.name} needs at least two free cells")
        self._fixed_goal = None if goal is None else self._resolve_goal(goal)
        self._dist_cache: dict[tuple[int, int], np.ndarray] = {}
        self.observation_space = gym.spaces.Discrete(self.encoder.n_states)
        self.action_space = gym.spaces.Discrete(self.encoder.n_actions)
        self._ranges = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
        self._status = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
        self._pose = (0.0, 0.0, 0.0)
        self._goal = (0, 0)
        self._phi = 0.0
        self._state = 0
        cells = self._h * self._w
        self._path = np.zeros((cells, 2), dtype=np.int64)
        self._wps = np.zeros((cells, 2))
        self._rem = np.zeros(cells)
        self._nwp = 1
        self._k = 0

    def _resolve_goal(self, goal) -> tuple[int, int]:
        if isinstance(goal, str):
            if goal not in self.gridmap.targets:
                raise MapError(f"map {self.gridmap.name} has no target {goal!r}")
            return self.gridmap.targets[goal]
        col, row = int(goal[0]), int(goal[1])
        if not self.gridmap.is_free(col, row):
            raise MapError(f"goal ({col},{row}) is {self.gridmap.why_not_free(col, row)}")
        return col, row

    def _dist(self, goal: tuple[int, int]) -> np.ndarray:
        if goal not in self._dist_cache:
            self._dist_cache[goal] = octile_distances(self.gridmap.occ, *goal)
        return self._dist_cache[goal]

    def _goal_xy(self) -> tuple[float, float]:
        return cell_centre(self._goal[0], self._goal[1], self._h, self._c)

    def _observe(self) -> int:
        x, y, th = self._pose
        sectors, sensors, edges, which = self._enc
        sense(self._occ, self._h, self._w, self._c, x, y, th, which, self._ranges, self._status, self._tw)
        tx, ty = self._wps[self._k]
        return int(encode_fast(bearing_mrad(x, y, th, tx, ty), self._ranges, self._status,
                               sectors, sensors, edges))

    def _info(self, **extra) -> dict[str, Any]:
        x, y, th = self._pose
        sensors = list(self.encoder.sensors)
        return {"x_mm": x, "y_mm": y, "heading_rad": th, "goal": self._goal,
                "waypoints": [(float(a), float(b)) for a, b in self._wps[:self._nwp]], "waypoint": self._k,
                "ranges_mm": self._ranges[sensors].copy(), "status": self._status[sensors].copy(),
                "potential_mm": self._phi, **extra}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        rng = self.np_random
        if "goal" in options:
            self._goal = self._resolve_goal(options["goal"])
        elif self._fixed_goal is not None:
            self._goal = self._fixed_goal
        else:
            self._goal = self._free[int(rng.integers(len(self._free)))]
        dist = self._dist(self._goal)
        if "start" in options:
            scol, srow = (int(v) for v in options["start"])
            if not self.gridmap.is_free(scol, srow) or not np.isfinite(dist[srow, scol]):
                raise MapError(f"start ({scol},{srow}) is not a free cell connected to the goal")
            x, y = cell_centre(scol, srow, self._h, self._c)
        else:
            starts = [cr for cr in self._free if cr != self._goal and np.isfinite(dist[cr[1], cr[0]])]
            if not starts:
                raise MapError(f"goal {self._goal} of map {self.gridmap.name} has no connected start cell")
            scol, srow = starts[int(rng.integers(len(starts)))]
            cx, cy = cell_centre(scol, srow, self._h, self._c)
            half = 0.5 * self._c - self.robot.radius_mm - 1.0
            x = cx + float(rng.uniform(-half, half))
            y = cy + float(rng.uniform(-half, half))
        th = float(options["heading"]) if "heading" in options else float(rng.uniform(-math.pi, math.pi))
        th = (th + math.pi) % (2 * math.pi) - math.pi
        self._pose = (x, y, th)
        gx, gy = self._goal_xy()
        self._nwp = int(start_guidance(self._occ, self._h, self._w, self._c, dist, x, y, gx, gy, self._guided,
                                       self._clear_r, self._max_seg, self._path, self._wps, self._rem))
        self._k = 0
        self._phi = float(guide_potential(dist, self._occ, self._h, self._w, self._c, x, y, self._wps,
                                          self._rem, 0, self._guided))
        self._state = self._observe()
        return self._state, self._info(success=False, collision=False, driven_mm=0.0)

    def step(self, action):
        a = int(action)
        if not self.action_space.contains(a):
            raise ValueError(f"action {action!r} outside {self.action_space}")
        x, y, th = self._pose
        sectors, sensors, edges, which = self._enc
        x, y, th, phi, r, s2, hit, success, driven, k = period_step(
            self._occ, self._h, self._w, self._c, self._dist(self._goal), x, y, th, self._phi,
            self._wps, self._rem, self._nwp, self._k, a, self._rw, which, self._ranges, self._status,
            sectors, sensors, edges, self._guided, self._tw)
        self._pose = (float(x), float(y), float(th))
        self._phi = float(phi)
        self._k = int(k)
        if s2 >= 0:
            self._state = int(s2)
        terminated = bool(hit or success)
        return self._state, float(r), terminated, False, self._info(
            success=bool(success), collision=bool(hit), driven_mm=float(driven))
