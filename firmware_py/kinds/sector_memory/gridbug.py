"""Cell-stepped Bug memory encoder (`GridBugEncoder` + `GridBugMemory`): the
sector state with memory at the grid level the paper's robot moves on (how the
robot steps from cell to cell on the table's relative moves: docs/training.md,
"Sector state with memory"). Its *reference heading*, kept in the memory, is the
direction of its last move, or the frame the mode rules set at a wall hit. No
position and no map enter the state:

* goal sector (8): for each axis of the reference frame, whether one cell
  move along it brings the robot closer to the goal (component > half a
  cell: + ; < -half a cell: - ; else 0), i.e. ahead, ahead-left, left,
  back-left, back, back-right, right, ahead-right (CCW from ahead; 0/0, in
  the goal cell, encodes as ahead): exactly "a move this way is goal-ward".
* free (4 bits): neighbour k (0 front, 1 left, 2 back, 3 right) is free when
  the range sensor looking that way (index 2k relative to the robot's
  physical grid heading) reads at least `free_mm` (the default and why: the
  doc section above). Too close -> blocked, too far -> free, invalid ->
  blocked (never drive into what was not seen).
* mode (3): go / follow the wall on the right / on the left, fixed rules
  (`update`), the Bug family's:
  - go -> wall mode when no free neighbour is goal-ward. The side is chosen
    at the first hit of a goal (goal to the left or straight ahead/behind:
    wall on the right) and kept for the goal; the goal distance there is the
    hit distance; the reference heading turns so that a blocked goal-ward
    cell is on the followed side (wall on the right: heading = that
    direction + 90 deg).
  - wall mode -> go when the goal distance is at least `leave_margin_mm`
    below the hit distance and a goal-ward neighbour is free (each new hit
    is closer than the last, so the robot cannot circle for ever).

State = go: sector * 16 + free; wall mode m (1, 2): 128 + (m - 1) * W + w,
with w = free (W = 16) or, with `wall_bearing`, sector * 16 + free (W = 128).
Integers only (the goal vector in mm, isqrt for the distance), as the robot's
control path. The ground station's twin has a jitted copy
(`ground_station.learn.sector_memory.kernels`) that a test compares with this one.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from firmware_py import robot_spec

# Grid directions (world frame, y north): 0 east (+x), 1 north (+y), 2 west, 3 south.
N_DIRS = 4
DIR_VECTORS: tuple[tuple[int, int], ...] = ((1, 0), (0, 1), (-1, 0), (0, -1))
DIR_HEADING_MRAD: tuple[int, ...] = (0, 1571, 3142, -1571)
# Relative moves (the table's actions): new direction = (reference heading + move) % 4.
MOVE_FORWARD, MOVE_LEFT, MOVE_BACK, MOVE_RIGHT = 0, 1, 2, 3
N_MOVES = 4
# Each move's one-cell step as (forward, left) in the reference frame: the .qtab action set of this kind.
MOVE_STEPS: tuple[tuple[int, int], ...] = ((1, 0), (0, 1), (-1, 0), (0, -1))
# Modes.
MODE_GO = 0
MODE_WALL_RIGHT = 1
MODE_WALL_LEFT = 2
N_MODES = 3
N_SECTORS = 8
N_FREE = 16
# (forward sign, left sign) -> sector, CCW from ahead; (0, 0) (the goal cell) encodes as ahead.
_SECTOR = {(1, 0): 0, (1, 1): 1, (0, 1): 2, (-1, 1): 3, (-1, 0): 4, (-1, -1): 5, (0, -1): 6, (1, -1): 7, (0, 0): 0}


def grid_dir_of(heading_mrad: int) -> int:
    """Nearest grid direction of a heading (mrad, any range); an exact diagonal goes counter-clockwise."""
    return ((heading_mrad + 785) // 1571) % N_DIRS


def rotate_into(dx: int, dy: int, direction: int) -> tuple[int, int]:
    """(forward, left) components of the world vector (dx, dy) in the frame facing `direction`."""
    d = direction % N_DIRS
    if d == 0:
        return dx, dy
    if d == 1:
        return dy, -dx
    if d == 2:
        return -dx, -dy
    return -dy, dx


def _sign_cell(v: int, cell_mm: int) -> int:
    """+1 if one cell move along +v brings the robot closer (2v > cell), -1 if along -v, else 0."""
    return 1 if 2 * v > cell_mm else -1 if 2 * v < -cell_mm else 0


@dataclass
class GridBugMemory:
    """What a `GridBugEncoder` keeps between cell moves of one goal: the
    mode, the side chosen at the first hit (0 = not yet), the hit distance
    (mm) and the reference heading (grid direction). `reset(direction)` on
    every new goal, with the grid direction the robot faces."""

    mode: int = MODE_GO
    side: int = 0
    hit_mm: int = 0
    heading: int = 0

    def reset(self, direction: int = 0) -> None:
        self.mode = MODE_GO
        self.side = 0
        self.hit_mm = 0
        self.heading = direction % N_DIRS

    def note_move(self, move: int) -> int:
        """Remember the relative move just taken; returns its world grid direction."""
        self.heading = (self.heading + move) % N_DIRS
        return self.heading


@dataclass(frozen=True)
class GridBugEncoder:
    """Cell-stepped Bug state: mode x goal sector x free neighbours (see the module docstring)."""

    free_mm: int = 350
    leave_margin_mm: int = 1
    cell_mm: int = robot_spec.DEFAULT_CELL_SIZE_MM
    wall_bearing: bool = False
    kind: str = field(default="sector-memory", init=False)

    def __post_init__(self) -> None:
        if not robot_spec.RANGE_MIN_MM < self.free_mm < robot_spec.RANGE_MAX_MM:
            raise ValueError(f"free_mm must be in ({robot_spec.RANGE_MIN_MM}, {robot_spec.RANGE_MAX_MM}), got {self.free_mm}")
        if self.leave_margin_mm < 0:
            raise ValueError(f"leave_margin_mm must be >= 0, got {self.leave_margin_mm}")
        if self.cell_mm < 1:
            raise ValueError(f"cell_mm must be >= 1, got {self.cell_mm}")

    @property
    def wall_states(self) -> int:
        return N_SECTORS * N_FREE if self.wall_bearing else N_FREE

    @property
    def n_states(self) -> int:
        return N_SECTORS * N_FREE + (N_MODES - 1) * self.wall_states

    @property
    def n_actions(self) -> int:
        return N_MOVES

    def free_mask(self, physical_dir: int, reference_dir: int, ranges_mm: list[int] | tuple[int, ...],
                  status: list[int] | tuple[int, ...] | None = None) -> int:
        """Bit k set when the neighbour in relative direction k of the
        reference heading is free, read from the sensor looking that way
        from the robot's physical grid heading."""
        mask = 0
        for k in range(N_DIRS):
            i = 2 * ((reference_dir + k - physical_dir) % N_DIRS)  # sensors are 45 deg apart, CCW
            st = robot_spec.RANGE_VALID if status is None else status[i]
            if st == robot_spec.RANGE_TOO_FAR or (st == robot_spec.RANGE_VALID and ranges_mm[i] >= self.free_mm):
                mask |= 1 << k
        return mask

    def signs(self, dx_mm: int, dy_mm: int, direction: int) -> tuple[int, int]:
        f, left = rotate_into(dx_mm, dy_mm, direction)
        return _sign_cell(f, self.cell_mm), _sign_cell(left, self.cell_mm)

    def goalward_mask(self, dx_mm: int, dy_mm: int, direction: int) -> int:
        """Bit k set when one cell move in relative direction k brings the robot closer to the goal."""
        sf, sl = self.signs(dx_mm, dy_mm, direction)
        return (sf == 1) | (sl == 1) << 1 | (sf == -1) << 2 | (sl == -1) << 3

    def update(self, memory: GridBugMemory, dx_mm: int, dy_mm: int, free_world: int) -> int:
        """Apply the mode rules; `free_world` has bit d set when the neighbour
        in world direction d is free. Returns the new mode."""
        dist = math.isqrt(dx_mm * dx_mm + dy_mm * dy_mm)
        gw = self.goalward_mask(dx_mm, dy_mm, 0)  # world frame: bit d = direction d is goal-ward
        if memory.mode != MODE_GO:
            if dist + self.leave_margin_mm <= memory.hit_mm and gw & free_world:
                memory.mode = MODE_GO
        elif gw and not gw & free_world:
            if memory.side == 0:
                _, left = rotate_into(dx_mm, dy_mm, memory.heading)
                memory.side = MODE_WALL_RIGHT if left >= 0 else MODE_WALL_LEFT
            memory.mode = memory.side
            memory.hit_mm = dist
            # the first goal-ward direction, counting CCW from the reference heading
            g = next(d for d in ((memory.heading + k) % N_DIRS for k in range(N_DIRS)) if gw >> d & 1)
            memory.heading = (g + 1) % N_DIRS if memory.side == MODE_WALL_RIGHT else (g + 3) % N_DIRS
        return memory.mode

    def encode(self, memory: GridBugMemory, dx_mm: int, dy_mm: int, physical_dir: int,
               ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...] | None = None) -> int:
        """Update `memory` for this decision, then the state index. (dx, dy):
        goal minus robot position (mm, world frame); `physical_dir`: the grid
        direction the robot faces. The caller reports the move it takes with
        `memory.note_move`."""
        free_world = self.free_mask(physical_dir, 0, ranges_mm, status)
        return self.encode_free(memory, dx_mm, dy_mm, free_world)

    def encode_free(self, memory: GridBugMemory, dx_mm: int, dy_mm: int, free_world: int) -> int:
        """`encode` from the world-frame free bits (bit d: neighbour in world direction d is free)."""
        mode = self.update(memory, dx_mm, dy_mm, free_world)
        h = memory.heading
        free = 0
        for k in range(N_DIRS):
            if free_world >> ((h + k) % N_DIRS) & 1:
                free |= 1 << k
        sector = _SECTOR[self.signs(dx_mm, dy_mm, h)]
        if mode == MODE_GO:
            return sector * N_FREE + free
        w = sector * N_FREE + free if self.wall_bearing else free
        return N_SECTORS * N_FREE + (mode - 1) * self.wall_states + w

    def to_dict(self) -> dict[str, object]:
        return asdict(self)
