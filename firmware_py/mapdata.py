"""The occupancy grid a policy carries to the robot (for the localiser), and which range readings it
explains (`unmapped_ends`, below: the collision monitor and the kinds that remember what the map
does not show ask it).

The map travels inside the `.qtab` file's metadata under `map_grid` (row strings, row 0 the
northernmost, `.` free and any of `@ T O W` occupied: docs/policy-format.md, "Metadata").
`grid_from_metadata` is the one parser: `firmware_py.policy.load_policy` calls it so a file whose
grid is malformed or does not match the header's map geometry is refused with a one-line reason
before it can be activated. Pure stdlib, no numpy.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from firmware_py import robot_spec

META_KEY = "map_grid"
FREE = "."
BLOCKED = frozenset("@TOW")
MAX_CELLS = 128 * 128  # metadata is bounded (policy.MAX_METADATA_BYTES); so is the grid
# ... and its extent: what the robot derives from a map (the localiser's likelihood field, the
# planners' rasters, global localisation's seeding) scales with the area in millimetres, so a
# legal cell count at a huge cell size must not buy unbounded work
MIN_CELL_MM = 50  # a fifth of the robot's width; smaller cells describe nothing it can use
MAX_SIDE_MM = 50_000  # a 50 m hall


class MapDataError(ValueError):
    """The map in a policy file is unusable; the message is a one-line reason."""


@dataclass(frozen=True)
class OccupancyGrid:
    """A map's cells: `occ[row * width + col]` is 1 for an occupied cell."""

    cell_mm: int
    width: int
    height: int
    occ: bytes

    def occupied(self, col: int, row: int) -> bool:
        """Occupied cell, and everything outside the grid (the world's outer walls)."""
        if not (0 <= col < self.width and 0 <= row < self.height):
            return True
        return self.occ[row * self.width + col] != 0

    def clearance_mm(self, x_mm: float, y_mm: float, reach_mm: float) -> float:
        """Distance from a world point (mm; x east, y north from the map's
        south-west corner) to the nearest occupied cell or the map's outside,
        looking `reach_mm` around (math.inf when none is that close)."""
        c = self.cell_mm
        best = math.inf
        for col in range(math.floor((x_mm - reach_mm) / c), math.floor((x_mm + reach_mm) / c) + 1):
            x0 = col * c
            dx = max(x0 - x_mm, 0.0, x_mm - (x0 + c))
            for south in range(math.floor((y_mm - reach_mm) / c), math.floor((y_mm + reach_mm) / c) + 1):
                if not self.occupied(col, self.height - 1 - south):
                    continue
                y0 = south * c
                d = math.hypot(dx, max(y0 - y_mm, 0.0, y_mm - (y0 + c)))
                best = min(best, d)
        return best

    def rows(self) -> list[str]:
        """The grid as metadata rows ('.' free, '@' occupied)."""
        w = self.width
        return ["".join("@" if self.occ[r * w + c] else FREE for c in range(w)) for r in range(self.height)]

    def summary(self) -> dict[str, Any]:
        return {"width": self.width, "height": self.height, "cell_mm": self.cell_mm,
                "occupied_cells": sum(1 for v in self.occ if v)}


def grid_from_rows(rows: list[str], cell_mm: int) -> OccupancyGrid:
    """Parse metadata rows; raises MapDataError with the first problem."""
    if not isinstance(rows, list) or not rows:
        raise MapDataError(f"{META_KEY} is not a non-empty list of row strings")
    if not all(isinstance(r, str) for r in rows):
        raise MapDataError(f"{META_KEY} has a row that is not a string")
    width = len(rows[0])
    if width == 0 or len(rows) * width > MAX_CELLS:
        raise MapDataError(f"{META_KEY} is {width}x{len(rows)} cells (allowed 1..{MAX_CELLS} cells)")
    occ = bytearray()
    for i, r in enumerate(rows):
        if len(r) != width:
            raise MapDataError(f"{META_KEY} row {i} has {len(r)} cells, row 0 has {width}")
        bad = next((ch for ch in r if ch != FREE and ch not in BLOCKED), None)
        if bad is not None:
            raise MapDataError(f"{META_KEY} row {i}: unknown cell {bad!r} (expected '.' or one of @TOW)")
        occ += bytes(ch in BLOCKED for ch in r)
    if not MIN_CELL_MM <= cell_mm <= MAX_SIDE_MM:
        raise MapDataError(f"{META_KEY}: cell size {cell_mm} mm (allowed {MIN_CELL_MM}..{MAX_SIDE_MM} mm)")
    side = max(width, len(rows)) * cell_mm
    if side > MAX_SIDE_MM:
        raise MapDataError(f"{META_KEY} is {width * cell_mm} x {len(rows) * cell_mm} mm "
                           f"(allowed up to {MAX_SIDE_MM} mm a side)")
    return OccupancyGrid(cell_mm, width, len(rows), bytes(occ))


def grid_from_metadata(metadata: dict[str, Any], cell_mm: int, width: int, height: int) -> OccupancyGrid | None:
    """The grid a policy's metadata carries (None: it carries none), checked
    against the header's map geometry (`cell_mm`, `width`, `height`)."""
    if META_KEY not in metadata:
        return None
    grid = grid_from_rows(metadata[META_KEY], cell_mm)
    if (grid.width, grid.height) != (width, height):
        raise MapDataError(f"{META_KEY} is {grid.width}x{grid.height} cells but the header's map geometry "
                           f"is {width}x{height}")
    return grid


def grid_from_map_file(path: str, cell_mm: int) -> OccupancyGrid:
    """The robot's own map from a MovingAI `.map` file (`type`, `height H`, `width W`, `map`, then H
    rows; `. G S` free, `@ O T W` walls; what `qnav` trains on): `qnav-robot --map FILE`. Raises
    MapDataError with the file and line of the first problem; the same bounds as a policy's grid."""
    try:
        with open(path, encoding="utf-8") as f:
            lines = [ln.rstrip("\r\n") for ln in f]
    except (OSError, UnicodeDecodeError) as exc:
        raise MapDataError(f"{path}: cannot read: {exc}") from None
    header: dict[str, str] = {}
    i = 0
    while i < len(lines) and lines[i].strip() != "map":
        key, _, value = lines[i].strip().partition(" ")
        header[key] = value.strip()
        i += 1
    try:
        height, width = int(header["height"]), int(header["width"])
    except (KeyError, ValueError):
        raise MapDataError(f"{path}: no 'height H' and 'width W' lines before 'map'") from None
    rows = lines[i + 1:i + 1 + height]
    if i >= len(lines) or len(rows) != height:
        raise MapDataError(f"{path}: {len(rows)} map rows after 'map', the header says {height}")
    for n, row in enumerate(rows):
        if len(row) != width:
            raise MapDataError(f"{path}:{i + 2 + n}: {len(row)} cells, the header says {width}")
        bad = next((ch for ch in row if ch not in ".GS@OTW"), None)
        if bad is not None:
            raise MapDataError(f"{path}:{i + 2 + n}: unknown character {bad!r} (free: . G S, wall: @ O T W)")
    rows = ["".join(FREE if ch in ".GS" else "@" for ch in row) for row in rows]
    try:
        return grid_from_rows(rows, cell_mm)
    except MapDataError as exc:
        raise MapDataError(f"{path}: {exc}") from None


def describe(grid: OccupancyGrid) -> str:
    return f"{grid.width}x{grid.height} cells of {grid.cell_mm} mm"


# --- which readings the map explains ---------------------------------------------------------------
# `unmapped_ends` / `unmapped_readings` tell which range readings the map does not explain: on no ray
# of the sensor's fan (the sensor geometry of `robot_spec`, as the twin's `sense` casts it) does the
# point at the read distance lie within `margin_mm` of an occupied cell or the map's edge. A disc, a
# box or a person in the open is unmapped; a map wall never is, also from a pose a little off (the
# margin absorbs the localiser's error) and also where a fan ray grazes a corner. The
# ray end points are computed in floats and rounded to whole mm; the wall test is integers. Any kind
# and the controller use them: the collision monitor (`control.collision.mapped_readings`), the sector
# kind's obstacle memory and the readings it withholds from the localiser.

MAP_MARGIN_MM = 150  # a reading is explained by the map within this distance of a mapped cell


@functools.lru_cache(maxsize=16)
def _fans(angles_mrad: tuple[int, ...], fov_mrad: int, mount_mm: int
          ) -> tuple[list[float], list[float], list[list[float]], list[list[float]], float]:
    """The sensor fans of a layout (the twin's `sense` casts the same rays): cos, sin per sensor and
    per ray, and the mount radius."""
    ang = [a / 1000.0 for a in angles_mrad]
    nr = robot_spec.SENSOR_FAN_RAYS
    fan = [(k / (nr - 1) - 0.5) * (fov_mrad / 1000.0) for k in range(nr)] if nr > 1 else [0.0]
    return ([math.cos(a) for a in ang], [math.sin(a) for a in ang], [[math.cos(a + f) for f in fan] for a in ang],
            [[math.sin(a + f) for f in fan] for a in ang], float(mount_mm))


def walls_near(grid: OccupancyGrid, x: int, y: int, m: int) -> Iterator[tuple[int, int]]:
    """(dx, dy) mm from the point (x, y) to each occupied cell (or the outside of the grid: the
    world's outer walls) whose square may lie within m mm (integers only; 0 along an axis inside)."""
    c = grid.cell_mm
    top = grid.height * c
    for row in range((top - (y + m)) // c, (top - (y - m)) // c + 1):
        ylo = top - (row + 1) * c
        dy = ylo - y if y < ylo else (y - ylo - c if y > ylo + c else 0)
        for col in range((x - m) // c, (x + m) // c + 1):
            if grid.occupied(col, row):
                xlo = col * c
                yield (xlo - x if x < xlo else (x - xlo - c if x > xlo + c else 0)), dy


def wall_within(grid: OccupancyGrid, x: int, y: int, m: int) -> bool:
    """An occupied cell (or the outside of the grid) has a point within m mm of the point (x, y) mm.
    `walls_near`'s cells, unrolled: every reading of every tick asks this (three rays a sensor)."""
    c = grid.cell_mm
    top = grid.height * c
    mm = m * m
    for row in range((top - (y + m)) // c, (top - (y - m)) // c + 1):
        ylo = top - (row + 1) * c
        dy = ylo - y if y < ylo else (y - ylo - c if y > ylo + c else 0)
        dy2 = dy * dy
        if dy2 > mm:
            continue
        for col in range((x - m) // c, (x + m) // c + 1):
            if grid.occupied(col, row):
                xlo = col * c
                dx = xlo - x if x < xlo else (x - xlo - c if x > xlo + c else 0)
                if dx * dx + dy2 <= mm:
                    return True
    return False


def wall_gap(grid: OccupancyGrid, x: int, y: int, m: int) -> float:
    """Distance (mm) from the point to the nearest occupied cell (or the outside of the grid), capped at m."""
    return min([float(m), *(math.hypot(dx, dy) for dx, dy in walls_near(grid, x, y, m))])


def unmapped_ends(grid: OccupancyGrid, x_mm: int, y_mm: int, heading_mrad: int,
                  ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
                  margin_mm: int, max_mm: int = robot_spec.RANGE_MAX_MM,
                  layout: Any = None) -> list[tuple[int, int, int, int]]:
    """(sensor, distance mm, x, y) per reading the map does not explain (section comment above), the
    point being the end of the fan's middle ray. Too far and invalid readings, and readings beyond
    max_mm, never count; a too-close reading is taken at the range's minimum. `layout`
    (firmware_py.layout.Layout; None: the built-in robot): where the sensors look."""
    if layout is None:
        fans = _fans(robot_spec.SENSOR_ANGLES_MRAD, robot_spec.SENSOR_FOV_MRAD, robot_spec.SENSOR_MOUNT_RADIUS_MM)
        rmin = robot_spec.RANGE_MIN_MM
    else:
        fans = _fans(layout.angles_mrad, layout.fov_mrad, layout.mount_mm)
        rmin = layout.range_min_mm
    sens_cos, sens_sin, ray_cos, ray_sin, mount = fans
    out: list[tuple[int, int, int, int]] = []
    th = heading_mrad / 1000.0
    ct = math.cos(th)
    st = math.sin(th)
    n_rays = robot_spec.SENSOR_FAN_RAYS
    mid = n_rays // 2
    for i in range(len(sens_cos)):
        if status[i] == robot_spec.RANGE_TOO_CLOSE:
            r = rmin
        elif status[i] == robot_spec.RANGE_VALID:
            r = ranges_mm[i]
        else:
            continue
        if r > max_mm:
            continue
        ox = x_mm + mount * (ct * sens_cos[i] - st * sens_sin[i])
        oy = y_mm + mount * (st * sens_cos[i] + ct * sens_sin[i])
        end = (0, 0)
        for k in range(n_rays):
            cx = ct * ray_cos[i][k] - st * ray_sin[i][k]
            cy = st * ray_cos[i][k] + ct * ray_sin[i][k]
            ex, ey = math.floor(ox + r * cx + 0.5), math.floor(oy + r * cy + 0.5)
            if wall_within(grid, ex, ey, margin_mm):
                break  # explained by the map
            if k == mid:
                end = (ex, ey)
        else:
            out.append((i, r, end[0], end[1]))
    return out


def unmapped_readings(grid: OccupancyGrid, x_mm: int, y_mm: int, heading_mrad: int,
                      ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
                      margin_mm: int, layout: Any = None) -> list[int]:
    """Per sensor: its distance (mm) when the map does not explain the
    reading (`unmapped_ends`; too close: 0), else -1."""
    out = [-1] * (robot_spec.SENSOR_COUNT if layout is None else layout.count)
    max_mm = robot_spec.RANGE_MAX_MM if layout is None else layout.max_range_mm
    for i, r, _, _ in unmapped_ends(grid, x_mm, y_mm, heading_mrad, ranges_mm, status, margin_mm, max_mm, layout):
        out[i] = 0 if status[i] == robot_spec.RANGE_TOO_CLOSE else r
    return out
