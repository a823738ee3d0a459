"""The reference of the sector trainer's noisy sensing (`ground_station.learn.sector.kernels`):
`noisy_state` adds the Gaussian noise to every valid reading and re-classifies it past the sensor
limits, as the sim's noisy sensors report; the kernels' `noisy_encode_fast` must give the same
state index with the same draws (tests/ground_station/test_sector_fast.py)."""

from __future__ import annotations

import math

from ground_station.jitcache import numba
from ground_station.learn.sector.kernels import (
    RANGE_MIN_,
    RANGE_TOO_CLOSE_,
    RANGE_TOO_FAR_,
    RANGE_VALID_,
    gauss,
)
from ground_station.learn.sector.twin import TW_RMAX, bearing_mrad, encode_fast


@numba.njit(cache=True)
def noisy_state(rng, noise_mm, x, y, th, tx, ty, ranges, status, noisy, nstatus, sectors, sensors, edges,
                tw) -> int:
    """State index from the readings with Gaussian noise (std noise_mm, whole mm) added to the
    valid ones, re-classified past the sensor limits, as the sim's noisy sensors report."""
    return noisy_encode(rng, noise_mm, bearing_mrad(x, y, th, tx, ty), ranges, status, noisy, nstatus,
                        sectors, sensors, edges, tw)


@numba.njit(cache=True, inline="always")
def noisy_encode(rng, noise_mm, bearing, ranges, status, noisy, nstatus, sectors, sensors, edges, tw) -> int:
    """`noisy_state` with the target's bearing (int mrad) already known."""
    for j in range(sensors.shape[0]):
        i = sensors[j]
        noisy[i] = ranges[i]
        nstatus[i] = status[i]
        if status[i] == RANGE_VALID_:
            r = ranges[i] + int(math.floor(noise_mm * gauss(rng) + 0.5))
            if r < RANGE_MIN_:
                noisy[i] = RANGE_MIN_
                nstatus[i] = RANGE_TOO_CLOSE_
            elif r > tw[TW_RMAX][i]:
                noisy[i] = int(tw[TW_RMAX][i])
                nstatus[i] = RANGE_TOO_FAR_
            else:
                noisy[i] = r
    return encode_fast(bearing, noisy, nstatus, sectors, sensors, edges)
