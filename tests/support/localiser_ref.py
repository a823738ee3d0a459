"""The localiser's sensor model for one pose, written plainly: what an update weighs each particle
by (firmware_py/control/localiser.py, `_weigh_chunk` and `_seed_tick`), the reference
tests/firmware_py/test_localiser.py and test_global_localisation.py check them against by hand; and
the likelihood field's values at a world point, looked up plainly."""

from __future__ import annotations

import math

from firmware_py.control.localiser import LikelihoodField, Localiser


def _index(field: LikelihoodField, x_mm: float, y_mm: float) -> int:
    """The raster index of a world point (-1 beyond the raster)."""
    fx = x_mm + field.margin
    fy = y_mm + field.margin
    if fx < 0 or fy < 0:
        return -1
    ix = int(fx / field.res)
    iy = int(fy / field.res)
    return -1 if ix >= field.nx or iy >= field.ny else iy * field.nx + ix


def signed_at(field: LikelihoodField, x_mm: float, y_mm: float) -> float:
    """The signed distance (mm, < 0 inside a wall, capped at max_mm) at a world point; beyond the
    raster: -max_mm (off the map)."""
    i = _index(field, x_mm, y_mm)
    return field.signed[i] if i >= 0 else -field.max_mm


def log_p(field: LikelihoodField, x_mm: float, y_mm: float) -> float:
    """The field at a world point; beyond the raster: the floor."""
    i = _index(field, x_mm, y_mm)
    return field.table[i] if i >= 0 else field.floor


def log_likelihood(loc: Localiser, x_mm: float, y_mm: float, heading_rad: float, ranges_mm: list[int],
                   status: list[int]) -> float:
    total = 0.0
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    for k, r in loc._readings(ranges_mm, status):
        d = loc._mount + r
        ends = [(x_mm + d * (c * ca - s * sa), y_mm + d * (s * ca + c * sa)) for ca, sa in loc._beams[k]]
        if loc.cfg.cone_min:
            m = min(signed_at(loc.field, ex, ey) for ex, ey in ends)
            total += loc.field.by_mm[int(abs(m))]
        else:
            total += max(log_p(loc.field, ex, ey) for ex, ey in ends)
    return loc.cfg.beam_weight * total
