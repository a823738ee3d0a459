"""The localiser's sensor model, precomputed once per map: the likelihood field
(`LikelihoodField`: per raster square the signed distance to the nearest wall
surface and its log-likelihood under the hit-plus-floor model), shared by every
localiser on the same map and model (`likelihood_field`). See
`firmware_py.control.localiser` for how the filter weighs readings with it.
"""

from __future__ import annotations

import functools
import math
from array import array

from firmware_py.mapdata import OccupancyGrid

MAX_FIELD_POINTS = 300_000  # raster squares of a likelihood field (bounds its build time and memory)


class LikelihoodField:
    """log(z_hit * exp(-d^2 / 2 sigma^2) + z_floor) on a `res_mm` raster of
    the map and a `max_mm` margin around it (end points of readings of the
    outer walls land there), d the distance (mm) from the square's centre to
    the nearest occupied cell or the outside of the map (0 inside them),
    capped at `max_mm`. Beyond the raster: the floor."""

    def __init__(self, grid: OccupancyGrid, res_mm: int, sigma_mm: float, z_hit: float, z_floor: float,
                 max_mm: float) -> None:
        self.grid = grid
        c = grid.cell_mm
        self.width_mm = grid.width * c
        self.height_mm = grid.height * c
        # a coarser raster on a large map: the work (and memory) stays under MAX_FIELD_POINTS
        # squares whatever the map's extent
        area = (self.width_mm + 2 * max_mm) * (self.height_mm + 2 * max_mm)
        res_mm = max(res_mm, math.ceil(math.sqrt(area / MAX_FIELD_POINTS)))
        while True:
            self.res = res_mm
            self.margin = -(-int(max_mm) // res_mm) * res_mm
            self.nx = -(-(self.width_mm + 2 * self.margin) // res_mm)
            self.ny = -(-(self.height_mm + 2 * self.margin) // res_mm)
            if self.nx * self.ny <= MAX_FIELD_POINTS:
                break
            res_mm += 1
        self.floor = math.log(z_floor)
        reach = max(1, math.ceil(max_mm / c))
        table = array("f", bytes(4 * self.nx * self.ny))
        two_s2 = 2 * sigma_mm * sigma_mm
        inside = bytearray(self.nx * self.ny)
        signed = array("f", bytes(4 * self.nx * self.ny))  # mm to the nearest wall surface, < 0 inside a wall
        far = math.log(z_hit * math.exp(-max_mm * max_mm / two_s2) + z_floor)  # d capped: most squares
        # Every square of one map cell looks at the same cells around it (`distance_mm`, `depth_mm`):
        # they are listed once per cell (`_cells_near`), so a square in open floor costs a lookup, not a
        # scan of (2 reach + 1)^2 cells (the build was 1 s for a 16 x 16 map of 0.5 m cells)
        near: dict[tuple[int, int], tuple[bool, list[tuple[float, float, float, float]]]] = {}
        xs = [(ix + 0.5) * res_mm - self.margin for ix in range(self.nx)]
        runs: list[tuple[int, int, int]] = []  # (col, first ix, end ix): the squares of one map column
        for ix, px in enumerate(xs):
            col = math.floor(px / c)
            if runs and runs[-1][0] == col:
                runs[-1] = (col, runs[-1][1], ix + 1)
            else:
                runs.append((col, ix, ix + 1))
        hypot = math.hypot
        for iy in range(self.ny):
            py = (iy + 0.5) * res_mm - self.margin
            row = grid.height - 1 - math.floor(py / c)
            base = iy * self.nx
            for col, first, end in runs:
                found = near.get((col, row))
                if found is None:
                    wall = grid.occupied(col, row)
                    found = near[(col, row)] = (wall, self._cells_near(col, row, reach, walls=not wall))
                wall, rects = found
                # a rectangle's distance along y is the same for the whole run
                across = [(x0, x1, max(y0 - py, 0.0, py - y1)) for x0, x1, y0, y1 in rects]
                for ix in range(first, end):
                    px = xs[ix]
                    d = math.inf
                    for x0, x1, dy in across:
                        dx = x0 - px
                        if dx <= 0.0:
                            dx = px - x1
                            if dx <= 0.0:
                                dx = 0.0
                        e = hypot(dx, dy)
                        if e < d:
                            d = e
                    inner = wall
                    if d == 0.0 and not wall:  # on a free cell's edge with a wall: counted in the wall
                        inner, d = True, self.depth_mm(px, py, reach)
                    if inner:  # inside a wall: as far from its surface as from the nearest free space
                        inside[base + ix] = 1
                    if d >= max_mm:
                        d = max_mm
                        table[base + ix] = far
                    else:
                        table[base + ix] = math.log(z_hit * math.exp(-d * d / two_s2) + z_floor)
                    signed[base + ix] = -d if inner else d
        self.table = table
        self.signed = signed.tolist()
        # the cone model's lookup: by_mm[i] is the field's value at i + 0.5 mm, the middle of the
        # distances that truncate to i (0 .. max_mm)
        self.by_mm = [math.log(z_hit * math.exp(-(d + 0.5) ** 2 / two_s2) + z_floor) for d in range(int(max_mm) + 1)]
        self.max_mm = int(max_mm)
        self.values = table.tolist()  # the same as a list: indexing it is faster in the weighing loop
        # squares inside an occupied cell or off the map (negative information: a reading saw through a wall)
        self.inside = inside

    def _cells_near(self, col: int, row: int, reach: int, walls: bool) -> list[tuple[float, float, float, float]]:
        """The cells within `reach` of cell (col, row), as (x0, x1, y0, y1) mm: with `walls` the
        occupied ones and the outside of the map (`distance_mm`), else the map's free ones
        (`depth_mm`)."""
        g = self.grid
        c = g.cell_mm
        if walls:
            rows, cols = range(row - reach, row + reach + 1), range(col - reach, col + reach + 1)
        else:
            rows = range(max(0, row - reach), min(g.height - 1, row + reach) + 1)
            cols = range(max(0, col - reach), min(g.width - 1, col + reach) + 1)
        return [(float(cc * c), float(cc * c + c), float((g.height - 1 - r) * c), float((g.height - r) * c))
                for r in rows for cc in cols if g.occupied(cc, r) == walls]

    @staticmethod
    def _nearest(px: float, py: float, cells: list[tuple[float, float, float, float]]) -> float:
        """Distance from (px, py) to the nearest of `cells` (inf for none)."""
        best = math.inf
        for x0, x1, y0, y1 in cells:
            d = math.hypot(max(x0 - px, 0.0, px - x1), max(y0 - py, 0.0, py - y1))
            if d < best:
                best = d
        return best

    def _cell_of(self, px: float, py: float) -> tuple[int, int]:
        c = self.grid.cell_mm
        return math.floor(px / c), self.grid.height - 1 - math.floor(py / c)

    def distance_mm(self, px: float, py: float, reach: int = 2) -> float:
        """Distance from a world point (mm) to the nearest occupied cell or
        the map's edge, looking `reach` cells around (exact below reach * cell)."""
        col, row = self._cell_of(px, py)
        if self.grid.occupied(col, row):
            return 0.0
        return self._nearest(px, py, self._cells_near(col, row, reach, walls=True))

    def depth_mm(self, px: float, py: float, reach: int = 2) -> float:
        """Distance from a world point inside an occupied cell or off the map to the nearest free
        cell of the map, looking `reach` cells around (inf when there is none that near). A reading
        ends on a wall's surface: an end point deep inside the wall (a pose too near the wall, or a
        heading that looks into it) explains it as badly as one short of it."""
        return self._nearest(px, py, self._cells_near(*self._cell_of(px, py), reach, walls=False))

    def free(self, x_mm: float, y_mm: float, clearance_mm: float) -> bool:
        """A robot centred here would not overlap a wall (for uniform draws)."""
        if not (0 <= x_mm < self.width_mm and 0 <= y_mm < self.height_mm):
            return False
        return self.distance_mm(x_mm, y_mm, 1) >= clearance_mm


@functools.lru_cache(maxsize=4)
def likelihood_field(grid: OccupancyGrid, res_mm: int, sigma_mm: float, z_hit: float, z_floor: float,
                     max_mm: float) -> LikelihoodField:
    """The field for a map and model, computed once (a reactivated policy, a
    new episode on the same map: no second precomputation). Fields are never
    written after construction, so sharing one is safe."""
    return LikelihoodField(grid, res_mm, sigma_mm, z_hit, z_floor, max_mm)
