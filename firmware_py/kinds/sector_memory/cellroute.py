"""Routes over the robot's own map for the cell-stepped Bug (`sector-memory`).

The Bug memory is complete but blind: with only the goal's bearing it follows
walls it could have known about, and on a maze or a house of rooms its path
is several times the shortest. The robot has its map (`qnav map upload`) and a
localised pose, so, as nav2's global planner feeds its controller, it gives the Bug sub-goals
along the map's shortest route and lets the learnt table and its memory deal
with what the map does not show (discs, movers, a door left shut).

* `CellRoute` holds the distance-to-goal field over the map's free cells
  (breadth-first, 4-connected, as the Bug moves), computed off the tick on
  the kind's `Background` and read on a later tick; until it is there the Bug
  steers on the goal.
* `straight_subgoal` picks, from a cell, the end of the longest straight
  run down the field: the Bug then sees its sub-goal dead ahead, and turns
  only where the route turns.

Pure stdlib, integers only; the field is a flat list indexed row * width +
col in the map's (col, row) cells (row 0 at the top, `robot_spec.world_to_cell`).
"""

from __future__ import annotations

from collections import deque
from typing import Any

from firmware_py.background import Background

UNREACHABLE = -1
# (dcol, drow) per grid direction: 0 east, 1 north (row decreases), 2 west, 3 south (gridbug.DIR_VECTORS)
DIR_CELLS: tuple[tuple[int, int], ...] = ((1, 0), (0, -1), (-1, 0), (0, 1))


def distance_field(grid: Any, goal: tuple[int, int]) -> list[int]:
    """Moves from every cell of `grid` (mapdata.OccupancyGrid) to `goal` (col, row) through free
    cells, 4-connected; UNREACHABLE for occupied or cut-off cells (all of them if the goal is
    occupied)."""
    w, h = grid.width, grid.height
    field = [UNREACHABLE] * (w * h)
    gc, gr = goal
    if grid.occupied(gc, gr):
        return field
    occ = grid.occ
    field[gr * w + gc] = 0
    todo = deque([(gc, gr)])
    while todo:
        c, r = todo.popleft()
        d = field[r * w + c] + 1
        for dc, dr in DIR_CELLS:
            nc, nr = c + dc, r + dr
            if 0 <= nc < w and 0 <= nr < h:
                i = nr * w + nc
                if field[i] == UNREACHABLE and not occ[i]:
                    field[i] = d
                    todo.append((nc, nr))
    return field


def straight_subgoal(field: list[int], width: int, height: int, cell: tuple[int, int],
                     prefer: int = -1) -> tuple[int, int] | None:
    """The end of the longest straight run from `cell` down `field` (each step one move nearer
    the goal); ties go to direction `prefer` (the way the robot faces), then the lowest. `cell`
    itself at the goal; None where the field does not reach `cell`."""
    c, r = cell
    if not (0 <= c < width and 0 <= r < height):
        return None
    d0 = field[r * width + c]
    if d0 == UNREACHABLE:
        return None
    if d0 == 0:
        return cell
    best: tuple[int, int, tuple[int, int]] | None = None  # (run length, preference, end cell)
    for d, (dc, dr) in enumerate(DIR_CELLS):
        n, (ec, er), want = 0, (c, r), d0 - 1
        while True:
            nc, nr = ec + dc, er + dr
            if not (0 <= nc < width and 0 <= nr < height) or field[nr * width + nc] != want:
                break
            n, ec, er, want = n + 1, nc, nr, want - 1
        if n and (best is None or (n, d == prefer) > best[:2]):
            best = (n, int(d == prefer), (ec, er))
    return best[2] if best is not None else None


class CellRoute:
    """The distance field to the current goal cell, computed on `work` (off the tick); `field`
    answers with it once it is there, None before (the caller steers on the goal meanwhile)."""

    def __init__(self, work: Background) -> None:
        self.work = work
        self._asked: tuple[Any, tuple[int, int]] | None = None  # (grid, goal cell) last posted
        self._ready: tuple[Any, tuple[int, int], list[int]] | None = None  # one assignment: thread-safe
        self.builds = 0

    def field(self, grid: Any, goal: tuple[int, int]) -> list[int] | None:
        ready = self._ready
        if ready is not None and ready[0] is grid and ready[1] == goal:
            return ready[2]
        asked = self._asked
        if asked is None or asked[0] is not grid or asked[1] != goal:
            self._asked = (grid, goal)
            self.work.post(self, lambda: self._build(grid, goal))
        return None

    def _build(self, grid: Any, goal: tuple[int, int]) -> None:
        field = distance_field(grid, goal)
        self.builds += 1
        self._ready = (grid, goal, field)
