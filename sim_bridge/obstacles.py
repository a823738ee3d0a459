"""Unmapped obstacles: static discs and moving discs the map does not show.

Owns the one definition of how a scenario's obstacles behave, shared by the pymunk plant
(`ObstacleLayer`, bodies its range rays and bumper see) and the ground station's kinematic twin
(`ground_station.learn.sector.obstacles` jit-compiles `step_movers` from this very source):

* a static obstacle is a disc (x, y, r) in mm, world frame (x east, y north);
* a mover is a disc (x, y, vx, vy, r, yields) (mm, mm/s) walking a straight line at constant speed.
  Once per control period it moves by v * dt, one axis at a time; an axis whose move would make it
  touch an obstacle cell, the map border or a static obstacle is not taken and that velocity
  component flips (it bounces). A mover that yields (yields = 1, the default: a pedestrian steps
  aside) also bounces off the robot plus `YIELD_MARGIN_MM`, so every contact is the robot's own
  doing; one that does not (yields = 0, `qnav bench nav --no-yield`) walks its own line through the
  robot's path and only stands still while it would overlap the robot (it stops on contact). Movers
  pass through each other. Five-column movers (before `yields`) yield.

Arrays, not objects, so the same function runs in numba and here: `discs` float64 (K, 3), `movers`
float64 (M, 6), `occ` the map grid (row 0 = north), `cell` mm.
"""

from __future__ import annotations

import math

import numpy as np
import pymunk

from firmware_py import robot_spec
from sim_bridge.world import World, as_wall

YIELD_MARGIN_MM = 60.0  # a mover keeps this much more than contact distance from the robot


def step_movers(movers, occ, cell, discs, rx, ry, rr, dt_s):  # type: ignore[no-untyped-def]
    """Advance every mover one period of dt_s in place (see the module docstring).

    (rx, ry, rr): the robot's centre and radius, mm. Plain Python on scalars
    and arrays so numba can compile it unchanged."""
    h = occ.shape[0]
    w = occ.shape[1]
    top = h * cell
    for i in range(movers.shape[0]):
        r = movers[i, 4]
        yields = movers.shape[1] < 6 or movers[i, 5] != 0.0
        for axis in range(2):
            nx = movers[i, 0]
            ny = movers[i, 1]
            if axis == 0:
                nx += movers[i, 2] * dt_s
            else:
                ny += movers[i, 3] * dt_s
            blocked = nx < r or ny < r or nx > w * cell - r or ny > top - r
            if not blocked:
                c0 = max(0, int(math.floor((nx - r) / cell)))
                c1 = min(w - 1, int(math.floor((nx + r) / cell)))
                r0 = max(0, int(math.floor((top - (ny + r)) / cell)))
                r1 = min(h - 1, int(math.floor((top - (ny - r)) / cell)))
                for row in range(r0, r1 + 1):
                    ylo = top - (row + 1) * cell
                    for col in range(c0, c1 + 1):
                        if occ[row, col]:
                            xlo = col * cell
                            px = min(max(nx, xlo), xlo + cell)
                            py = min(max(ny, ylo), ylo + cell)
                            if (nx - px) * (nx - px) + (ny - py) * (ny - py) < r * r:
                                blocked = True
            if not blocked:
                for k in range(discs.shape[0]):
                    dd = r + discs[k, 2]
                    if (nx - discs[k, 0]) ** 2 + (ny - discs[k, 1]) ** 2 < dd * dd:
                        blocked = True
                dd = r + rr + (YIELD_MARGIN_MM if yields else 0.0)  # refused only a step nearer: one the robot
                d2 = (nx - rx) ** 2 + (ny - ry) ** 2  # came up to within dd steps away (it froze, issue 47)
                if d2 < dd * dd and d2 < (movers[i, 0] - rx) ** 2 + (movers[i, 1] - ry) ** 2:
                    if not yields:
                        continue  # it does not step aside: it stands until the robot is out of its way
                    blocked = True
            if blocked:
                movers[i, 2 + axis] = -movers[i, 2 + axis]
            else:
                movers[i, 0] = nx
                movers[i, 1] = ny


def mover_array(movers) -> np.ndarray:  # type: ignore[no-untyped-def]
    """float64 (M, 6) from movers of five (x, y, vx, vy, r: they yield) or six values."""
    rows = [tuple(m) + (1.0,) * (6 - len(m)) for m in (movers if movers is not None else [])]
    for row in rows:
        if len(row) != 6:
            raise ValueError(f"a mover is x, y, vx, vy, r[, yields]: got {len(row)} values")
    return np.asarray(rows, dtype=np.float64).reshape(-1, 6)


class ObstacleLayer:
    """A scenario's obstacles in a pymunk `World`: static discs and kinematic mover discs, with the
    walls' collision type and category so the range rays hit them and a touch counts as bumper
    contact. `step()` once per control period moves the movers by `step_movers`."""

    def __init__(self, world: World, discs: list | None = None, movers: list | None = None) -> None:
        self.world = world
        self.discs = np.asarray(discs or [], dtype=np.float64).reshape(-1, 3)  # (K, 3)
        self.movers = mover_array(movers)
        self._occ = np.ascontiguousarray(world.occ, dtype=np.uint8)
        self._cell_mm = world.cell_size_m * 1000.0
        space = world.space
        for x, y, r in self.discs:
            space.add(as_wall(pymunk.Circle(space.static_body, r / 1000.0, (x / 1000.0, y / 1000.0))))
        self.bodies: list[pymunk.Body] = []
        for x, y, _vx, _vy, r, _yields in self.movers:
            body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
            body.position = (x / 1000.0, y / 1000.0)
            space.add(body, as_wall(pymunk.Circle(body, r / 1000.0)))
            self.bodies.append(body)

    def step(self, dt_s: float = robot_spec.CONTROL_PERIOD_US / 1e6) -> None:
        """Move the movers one control period (those that yield, round the robot's pose now)."""
        if not len(self.movers):
            return
        pose = self.world.pose
        step_movers(self.movers, self._occ, self._cell_mm, self.discs, pose.x * 1000.0, pose.y * 1000.0,
                    float(self.world.geometry.robot_radius_mm), dt_s)  # the profile's body
        for body, (x, y, *_rest) in zip(self.bodies, self.movers, strict=True):
            body.position = (x / 1000.0, y / 1000.0)
        for body in self.bodies:
            self.world.space.reindex_shapes_for_body(body)

    def positions_mm(self) -> list[tuple[float, float, float]]:
        """(x, y, r) of every mover now."""
        return [(float(x), float(y), float(r)) for x, y, _vx, _vy, r, _yields in self.movers]
