"""The localiser's sensor model for one pose, written plainly: what an update weighs each particle
by (firmware_py/control/localiser.py, `_weigh_chunk` and `_seed_tick`), the reference
tests/firmware_py/test_localiser.py and test_global_localisation.py check them against by hand."""

from __future__ import annotations

import math

from firmware_py.control.localiser import Localiser


def log_likelihood(loc: Localiser, x_mm: float, y_mm: float, heading_rad: float, ranges_mm: list[int],
                   status: list[int]) -> float:
    total = 0.0
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    for k, r in loc._readings(ranges_mm, status):
        d = loc._mount + r
        ends = [(x_mm + d * (c * ca - s * sa), y_mm + d * (s * ca + c * sa)) for ca, sa in loc._beams[k]]
        if loc.cfg.cone_min:
            m = min(loc.field.signed_at(ex, ey) for ex, ey in ends)
            total += loc.field.by_mm[int(abs(m))]
        else:
            total += max(loc.field.log_p(ex, ey) for ex, ey in ends)
    return loc.cfg.beam_weight * total
