"""Sweeps as Ray Tune experiments: one trial per job, resumable.

The job list is expanded on the driver (`campaign.space`), so Tune gets an
explicit grid over job indices: Tune's own searchers are not used, and the
same seeded sweep gives the same trials on Tune as on the local pool. Each
trial reports its result as one JSON string (Tune flattens nested metrics);
the experiment folder is Tune's own (`tune/<name>/`, with per-trial
`result.json`), and re-running the same command after an interruption
restores it (`Tuner.restore`) and runs only the trials that did not finish.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ground_station.errors import CliError
from ground_station.lab.campaign.engines import Engine, RayEngine, RunStats, import_ray

EXPERIMENT = "sweep"


def _trial(config: dict[str, Any], fn: Callable[[Any], Any]) -> None:
    """A Tune trainable: run one job and report its result once."""
    import ray
    from ray import tune

    item = config["item"]
    t0 = time.perf_counter()
    result = fn(item["job"])
    tune.report({"result_json": json.dumps(result), "job_index": item["index"],
                 "job_s": time.perf_counter() - t0,
                 "node": ray.get_runtime_context().get_node_id()})


def _trial_dirname(trial: Any) -> str:
    return f"job_{trial.config['item']['index']:05d}_{trial.trial_id}"


def run_on_tune(fn: Callable[[Any], Any], jobs: list[Any], tune_dir: Path, engine: Engine | None = None,
                progress: bool = True) -> tuple[list[Any], RunStats]:
    """Run `fn(job)` for each job as a Tune trial under `tune_dir`; results in job order.

    `engine` must be a RayEngine (it owns the Ray connection: a private local
    instance or the cluster at --ray-address)."""
    import_ray()
    from ray import tune

    own = engine is None
    if engine is None:
        engine = RayEngine()
    if not isinstance(engine, RayEngine):
        raise CliError("Tune sweeps need --engine ray")
    tune_dir = Path(tune_dir).resolve()
    path = tune_dir / EXPERIMENT
    trainable = tune.with_resources(tune.with_parameters(_trial, fn=fn), {"cpu": 1})
    # One grid axis over the explicit jobs (each tagged with its index, to put results back in order).
    space = {"item": tune.grid_search([{"index": i, "job": job} for i, job in enumerate(jobs)])}
    t0 = time.perf_counter()
    try:
        if tune.Tuner.can_restore(str(path)):
            tuner = tune.Tuner.restore(str(path), trainable=trainable, resume_errored=True,
                                       param_space=space)
        else:
            tuner = tune.Tuner(
                trainable,
                param_space=space,
                # a campaign's trials are short jobs: the next one reuses a finished trial's actor
                # instead of starting a Ray worker process (Ray, Tune and the job's imports) per trial
                tune_config=tune.TuneConfig(max_concurrent_trials=engine.workers, reuse_actors=True,
                                            trial_dirname_creator=_trial_dirname),
                run_config=tune.RunConfig(name=EXPERIMENT, storage_path=str(tune_dir),
                                          verbose=1 if progress else 0))
        grid = tuner.fit()
    finally:
        if own:
            engine.close()
    stats = RunStats("ray-tune", engine.workers, len(jobs))
    out: list[Any] = [None] * len(jobs)
    for k in range(len(grid)):
        res = grid[k]
        if res.error is not None or not res.metrics or "result_json" not in res.metrics:
            raise CliError(f"a Tune trial failed ({res.path}): {res.error}")
        i = int(res.metrics["job_index"])
        out[i] = json.loads(res.metrics["result_json"])
        stats.add(str(res.metrics.get("node", "?")), float(res.metrics.get("job_s", 0.0)))
    missing = [i for i, r in enumerate(out) if r is None]
    if missing:
        raise CliError(f"Tune experiment {path} lacks results for jobs {missing[:5]}")
    stats.wall_s = time.perf_counter() - t0
    return out, stats
