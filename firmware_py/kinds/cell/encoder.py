"""The cell kind's reference state encoder (the paper's grid):
state = goal_index * (W * H) + row * W + col.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from firmware_py import robot_spec


@dataclass(frozen=True)
class CellEncoder:
    """Robot cell on a W x H grid, times the goal index when there are several."""

    width: int
    height: int
    n_goals: int = 1
    kind: str = field(default="cell", init=False)

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1 or self.n_goals < 1:
            raise ValueError("width, height and n_goals must be >= 1")

    @property
    def n_states(self) -> int:
        return self.width * self.height * self.n_goals

    @property
    def n_actions(self) -> int:
        return len(robot_spec.CELL_ACTION_DELTAS)

    def encode(self, col: int, row: int, goal_index: int = 0) -> int:
        if not (0 <= col < self.width and 0 <= row < self.height and 0 <= goal_index < self.n_goals):
            raise ValueError(f"cell ({col},{row}) goal {goal_index} outside the {self.width}x{self.height}x{self.n_goals} grid")
        return (goal_index * self.height + row) * self.width + col

    def to_dict(self) -> dict[str, object]:
        return asdict(self)
