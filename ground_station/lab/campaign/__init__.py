"""Campaigns: many independent seeded jobs (sweeps, benchmark episodes) run on
the local process pool (default) or on Ray, with results that depend only on
the jobs. `engines` owns where jobs run, `space` the search spaces over
TrainConfig, `tune` sweeps as Ray Tune experiments."""
