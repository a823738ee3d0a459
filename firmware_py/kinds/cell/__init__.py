"""The `cell` kind: the paper's grid state (robot cell x goal index) over a map
whose cells the robot drives on; one table decision per cell move, executed by
the cell stepper. Encoder section: u16 width, height, n_goals, cell_mm; the goal
cells (u16 col, row each); then the action pairs (dcol, drow).
"""

from __future__ import annotations

import struct
from typing import Any, cast

from firmware_py import robot_spec
from firmware_py.control.odometry import wrap_mrad
from firmware_py.kinds.base import DriveTick, Geometry, Goals, Policy, PolicyKind, Unpacked
from firmware_py.kinds.cell.encoder import CellEncoder
from firmware_py.kinds.stepper import CellStepper, Step

_HEAD = struct.Struct("<HHHH")  # width, height, n_goals, cell_mm
_GOAL = struct.Struct("<HH")  # goal cell (col, row)
_PAIR_SIZE = 4
# grid action (dcol, drow) -> world heading (mrad): rows grow southwards
GRID_HEADING = {(1, 0): 0, (0, -1): 1571, (-1, 0): 3142, (0, 1): -1571}


def unpack(sec: bytes, n_actions: int, _expect_sensors: int) -> Unpacked:
    if len(sec) < _HEAD.size:
        raise ValueError("cell encoder section too short")
    width, height, n_goals, cell_mm = _HEAD.unpack_from(sec, 0)
    need = _HEAD.size + _GOAL.size * n_goals + _PAIR_SIZE * n_actions
    if len(sec) != need:
        raise ValueError(f"cell encoder section is {len(sec)} bytes, its fields need {need}")
    if width < 1 or height < 1 or n_goals < 1:
        raise ValueError(f"cell encoder: grid {width}x{height} with {n_goals} goals")
    if cell_mm < 1:
        raise ValueError("cell encoder: cell size is 0 mm")
    off = _HEAD.size
    goals = tuple(_GOAL.unpack_from(sec, off + _GOAL.size * i) for i in range(n_goals))
    for col, row in goals:
        if col >= width or row >= height:
            raise ValueError(f"cell encoder: goal ({col},{row}) outside the {width}x{height} grid")
    enc = CellEncoder(width=width, height=height, n_goals=n_goals)
    return Unpacked(enc, goals, cell_mm, off + _GOAL.size * n_goals)


def pack(enc: CellEncoder, goals: Goals, cell_mm: int) -> bytes:
    if len(goals) != enc.n_goals:
        raise ValueError(f"{len(goals)} goal cells for an encoder with {enc.n_goals} goals")
    return _HEAD.pack(enc.width, enc.height, enc.n_goals, cell_mm) + b"".join(
        _GOAL.pack(int(c), int(r)) for c, r in goals)


def fixed_geometry(enc: CellEncoder, cell_mm: int) -> Geometry:
    return (cell_mm, enc.width, enc.height)


def goal_index(policy: Policy, x_mm: int, y_mm: int, _radius_mm: int = robot_spec.ROBOT_RADIUS_MM) -> tuple[int, str]:
    """A goal must be one of the cell policy's target cells (a point off the map or
    in a wall is named as such first, when the policy carries its map)."""
    grid = policy.map_grid
    if grid is not None:
        if not (0 <= x_mm < grid.width * grid.cell_mm and 0 <= y_mm < grid.height * grid.cell_mm):
            return -1, f"goal ({x_mm}, {y_mm}) mm is outside the map"
        if grid.occupied(*robot_spec.world_to_cell(x_mm, y_mm, grid.height, grid.cell_mm)):
            return -1, f"goal ({x_mm}, {y_mm}) mm is inside a wall"
    col, row = robot_spec.world_to_cell(x_mm, y_mm, cast(CellEncoder, policy.encoder).height, policy.cell_mm)
    if (col, row) in policy.goals:
        return policy.goals.index((col, row)), ""
    return -1, f"goal cell ({col},{row}) is not a policy target"


def header_fields(policy: Policy) -> dict[str, Any]:
    return {"goals": [list(g) for g in policy.goals], "cell_mm": policy.cell_mm}


class CellDriver(CellStepper):
    """Localise the cell, greedy grid action -> the next cell centre and its heading."""

    def next_step(self, tick: DriveTick) -> Step | str:
        pol = self.policy
        enc = cast(CellEncoder, pol.encoder)
        x, y, heading = tick.pose_mm
        col, row = robot_spec.world_to_cell(x, y, enc.height, pol.cell_mm)
        if not (0 <= col < enc.width and 0 <= row < enc.height):
            return f"localisation: cell ({col},{row}) off the map"
        if (col, row) == robot_spec.world_to_cell(*tick.goal, enc.height, pol.cell_mm):
            return Step(tick.goal, wrap_mrad(heading + tick.goal_vector(*tick.goal)[1]))
        s = enc.encode(col, row, tick.goal_index)
        a = pol.best_action(s)
        dc, dr = robot_spec.CELL_ACTION_DELTAS[a]
        return Step(robot_spec.cell_center_mm(col + dc, row + dr, enc.height, pol.cell_mm), GRID_HEADING[(dc, dr)],
                    self.decided(s, a))


KIND = PolicyKind(name="cell", code=1, actions=tuple((dc, dr) for dc, dr in robot_spec.CELL_ACTION_DELTAS),
                  unpack=unpack, pack=pack, driver=CellDriver, fixed_geometry=fixed_geometry,
                  robot_cell_mm=lambda policy: policy.cell_mm, goal_index=goal_index, header_fields=header_fields,
                  map_specific=True)
