"""The in-memory grid map: occupancy plus named targets.

Row 0 is the first text row of a MovingAI file, i.e. the northernmost row in
the world frame of `firmware_py.robot_spec` (x east along columns, y north).
Targets are (col, row) pairs, ordered: their order is the goal index of the
cell encoding.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class MapError(ValueError):
    """A malformed or inconsistent map; the message is one line."""


@dataclass
class GridMap:
    """Occupancy grid (True = obstacle) with named targets."""

    name: str
    occ: np.ndarray  # bool (H, W), True = obstacle
    targets: dict[str, tuple[int, int]] = field(default_factory=dict)  # name -> (col, row), ordered
    cell_size_m: float = 0.5

    def __post_init__(self) -> None:
        self.occ = np.ascontiguousarray(np.asarray(self.occ, dtype=bool))
        if self.occ.ndim != 2 or self.occ.shape[0] < 1 or self.occ.shape[1] < 1:
            raise MapError(f"map {self.name}: occupancy must be a non-empty 2-D array, got shape {self.occ.shape}")
        if not self.cell_size_m > 0:
            raise MapError(f"map {self.name}: cell size must be positive, got {self.cell_size_m}")
        clean: dict[str, tuple[int, int]] = {}
        for tname, pos in self.targets.items():
            col, row = (int(v) for v in pos)
            if not self.is_free(col, row):
                raise MapError(f"map {self.name}: target {tname} at ({col},{row}) is {self.why_not_free(col, row)}")
            clean[str(tname)] = (col, row)
        self.targets = clean

    @property
    def height(self) -> int:
        return int(self.occ.shape[0])

    @property
    def width(self) -> int:
        return int(self.occ.shape[1])

    def in_bounds(self, col: int, row: int) -> bool:
        return 0 <= col < self.width and 0 <= row < self.height

    def is_free(self, col: int, row: int) -> bool:
        """True if (col, row) is inside the map and not an obstacle."""
        return self.in_bounds(col, row) and not bool(self.occ[row, col])

    def why_not_free(self, col: int, row: int) -> str:
        """'' for a free cell, else what it is: outside the map (its size named) or a wall."""
        if not self.in_bounds(col, row):
            return f"outside the {self.width}x{self.height} map {self.name}"
        if self.occ[row, col]:
            return f"a wall of map {self.name}"
        return ""

    def free_cells(self) -> list[tuple[int, int]]:
        """All free cells as (col, row), in row-major order."""
        rows, cols = np.nonzero(~self.occ)
        return [(int(c), int(r)) for r, c in zip(rows, cols, strict=True)]
