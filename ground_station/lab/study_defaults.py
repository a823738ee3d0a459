"""Defaults of the sector part of `qnav study` (`ground_station.lab.study`),
apart so that building the `qnav` parser imports neither numpy nor numba."""

SECTOR_STEPS = 2_000_000  # the shipped sector recipe compressed 10x (its schedules scale with the steps)
SECTOR_EVAL_EVERY = 250_000  # greedy checkpoint period
SECTOR_SAMPLE = 1000  # (start, goal, heading) episodes of every greedy checkpoint, fixed seed
