"""Issue 29 finding 7: a goal on the map's edge or inside a wall was accepted
for sector policies and driven at until the bumper. Every kind that carries
its map now refuses, with the reason, a goal outside the map, in a wall or
closer to one than the robot's radius. `set_goal` (SET_POSITION_TARGET,
DO_REPOSITION) and `set_mission` share the check (`_goal_index_for`); the
mission path is driven here, as it needs no armed robot."""

from __future__ import annotations

import pytest

from firmware_py import robot_spec
from firmware_py.control.controller import Controller
from firmware_py.policy import load_policy
from firmware_py.shipped_policies import resolve_policy_spec
from firmware_py.vehicle import VehicleConfig


@pytest.mark.parametrize("name", ["sector", "sector_memory"])
def test_goals_outside_free_space_are_refused_with_the_reason(name):
    pol = load_policy(resolve_policy_spec(f"policies:{name}"))
    grid = pol.map_grid
    ctrl = Controller(VehicleConfig(), pol)
    c, h = grid.cell_mm, grid.height
    wall = next((col, row) for row in range(h) for col in range(grid.width) if grid.occupied(col, row))
    free = next((col, row) for row in range(h) for col in range(grid.width)
                if all(not grid.occupied(col + dc, row + dr) for dc in (-1, 0, 1) for dr in (-1, 0, 1)))
    fx, fy = robot_spec.cell_center_mm(*free, h, c)
    wx, wy = robot_spec.cell_center_mm(*wall, h, c)
    refused = {
        (grid.width * c + 100, fy): "outside the map",
        (fx, -1): "outside the map",
        (wx, wy): "inside a wall",
        (0, fy): "0 mm from a wall",  # on the map's edge
        (100, fy): "100 mm from a wall (robot radius 150)",
    }
    for (x, y), needle in refused.items():
        ok, why = ctrl.set_mission([(fx, fy), (x, y)])
        assert not ok and why.startswith("item 1: ") and needle in why, (x, y, why)
    assert ctrl.set_mission([(fx, fy)]) == (True, "")


def test_a_cell_policy_names_a_goal_off_the_map_or_in_a_wall():
    """Issue 30 finding 7: a goal in a wall was refused as "not a policy target"."""
    pol = load_policy(resolve_policy_spec("policies:paper10_cell"))
    grid = pol.map_grid
    ctrl = Controller(VehicleConfig(), pol)
    c, h = grid.cell_mm, grid.height
    wall = next((col, row) for row in range(h) for col in range(grid.width) if grid.occupied(col, row))
    wx, wy = robot_spec.cell_center_mm(*wall, h, c)
    assert ctrl.set_mission([(wx, wy)]) == (False, f"item 0: goal ({wx}, {wy}) mm is inside a wall")
    ok, why = ctrl.set_mission([(grid.width * c + 200, 250)])
    assert not ok and why.endswith("is outside the map"), why
    free_not_target = next((col, row) for row in range(h) for col in range(grid.width)
                           if not grid.occupied(col, row) and (col, row) not in pol.goals)
    fx, fy = robot_spec.cell_center_mm(*free_not_target, h, c)
    ok, why = ctrl.set_mission([(fx, fy)])
    assert not ok and why.endswith("is not a policy target"), why
