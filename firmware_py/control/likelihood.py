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
        for iy in range(self.ny):
            py = (iy + 0.5) * res_mm - self.margin
            for ix in range(self.nx):
                px = (ix + 0.5) * res_mm - self.margin
                d = self.distance_mm(px, py, reach)
                if d == 0.0:  # inside a wall: as far from its surface as from the nearest free space
                    inside[iy * self.nx + ix] = 1
                    d = self.depth_mm(px, py, reach)
                d = min(d, max_mm)
                table[iy * self.nx + ix] = math.log(z_hit * math.exp(-d * d / two_s2) + z_floor)
                signed[iy * self.nx + ix] = -d if inside[iy * self.nx + ix] else d
        self.table = table
        self.signed = signed.tolist()
        # the cone model's lookup: by_mm[i] is the field's value at i + 0.5 mm, the middle of the
        # distances that truncate to i (0 .. max_mm)
        self.by_mm = [math.log(z_hit * math.exp(-(d + 0.5) ** 2 / two_s2) + z_floor) for d in range(int(max_mm) + 1)]
        self.max_mm = int(max_mm)
        self.values = table.tolist()  # the same as a list: indexing it is faster in the weighing loop
        # squares inside an occupied cell or off the map (negative information: a reading saw through a wall)
        self.inside = inside

    def distance_mm(self, px: float, py: float, reach: int = 2) -> float:
        """Distance from a world point (mm) to the nearest occupied cell or
        the map's edge, looking `reach` cells around (exact below reach * cell)."""
        g = self.grid
        c = g.cell_mm
        col = math.floor(px / c)
        row = g.height - 1 - math.floor(py / c)
        if g.occupied(col, row):
            return 0.0
        best = math.inf
        for r in range(row - reach, row + reach + 1):
            y0 = (g.height - 1 - r) * c
            y1 = y0 + c
            dy = max(y0 - py, 0.0, py - y1)
            for cc in range(col - reach, col + reach + 1):
                if not g.occupied(cc, r):
                    continue
                x0 = cc * c
                dx = max(x0 - px, 0.0, px - (x0 + c))
                d = math.hypot(dx, dy)
                if d < best:
                    best = d
        return best

    def depth_mm(self, px: float, py: float, reach: int = 2) -> float:
        """Distance from a world point inside an occupied cell or off the map to the nearest free
        cell of the map, looking `reach` cells around (inf when there is none that near). A reading
        ends on a wall's surface: an end point deep inside the wall (a pose too near the wall, or a
        heading that looks into it) explains it as badly as one short of it."""
        g = self.grid
        c = g.cell_mm
        col = math.floor(px / c)
        row = g.height - 1 - math.floor(py / c)
        best = math.inf
        for r in range(max(0, row - reach), min(g.height - 1, row + reach) + 1):
            y0 = (g.height - 1 - r) * c
            dy = max(y0 - py, 0.0, py - (y0 + c))
            for cc in range(max(0, col - reach), min(g.width - 1, col + reach) + 1):
                if g.occupied(cc, r):
                    continue
                x0 = cc * c
                d = math.hypot(max(x0 - px, 0.0, px - (x0 + c)), dy)
                if d < best:
                    best = d
        return best

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
