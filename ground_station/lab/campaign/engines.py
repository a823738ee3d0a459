"""Where a campaign's jobs run: the local process pool or a Ray cluster.

A campaign is a list of independent, self-seeded jobs (one training run, or
a batch of seeded episodes) and one top-level function that runs a job.
`Engine.map` runs them and returns the results in job order, so a result
file depends only on the jobs, never on the engine, the number of workers
or the order in which they finished.

`LocalEngine` is the embedded default (a fork pool over the local cores,
no extra dependency). `RayEngine` submits one Ray task per job to a local
Ray instance or to a cluster (`--ray-address`); Ray is imported only here
and only when asked for (`pip install 'qnav[cluster]'`).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import socket
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from ground_station.errors import CliError

ENGINES = ("local", "ray")
RAY_INSTALL_HINT = "Ray is not installed: pip install 'qnav[cluster]' (or: pip install 'ray[tune]')"


@dataclass
class RunStats:
    """What a `map` call cost: engine, workers, wall time and where jobs ran."""

    engine: str
    workers: int
    jobs: int
    wall_s: float = 0.0
    job_s: float = 0.0  # the jobs' own run times, summed: what one core would need
    nodes: dict[str, int] = field(default_factory=dict)  # node -> jobs run there

    def add(self, node: str, seconds: float) -> None:
        self.nodes[node] = self.nodes.get(node, 0) + 1
        self.job_s += seconds

    @property
    def speedup(self) -> float:
        """Sum of job times over the campaign's wall time: the speedup over one core."""
        return self.job_s / self.wall_s if self.wall_s > 0 else 0.0

    def as_dict(self) -> dict[str, Any]:
        return {"engine": self.engine, "workers": self.workers, "jobs": self.jobs,
                "wall_s": round(self.wall_s, 3), "job_s": round(self.job_s, 3),
                "speedup_over_one_core": round(self.speedup, 2), "nodes": dict(sorted(self.nodes.items()))}

    def summary(self) -> str:
        return (f"engine {self.engine}, {self.workers} workers on {len(self.nodes)} node(s): {self.jobs} jobs, "
                f"{self.wall_s:.1f} s wall, {self.job_s:.1f} s of job time, "
                f"speedup over one core {self.speedup:.2f}x")


def _local_node() -> str:
    return socket.gethostname()


def _call(fn: Callable[[Any], Any], job: Any) -> tuple[Any, str, float]:
    t0 = time.perf_counter()
    res = fn(job)
    return res, _local_node(), time.perf_counter() - t0


def _call_indexed(args: tuple[Callable[[Any], Any], int, Any]) -> tuple[int, Any, str, float]:
    fn, i, job = args
    return (i, *_call(fn, job))


class Engine(ABC):
    """Runs a campaign's jobs; results come back in job order."""

    name: str
    workers: int

    @abstractmethod
    def map(self, fn: Callable[[Any], Any], jobs: Sequence[Any], *, desc: str = "jobs",
            progress: bool = True, unit: str = "job") -> tuple[list[Any], RunStats]:
        """Run `fn(job)` for every job (fn must be a module-level function)."""

    def close(self) -> None:  # noqa: B027 - engines without resources need nothing
        """Release what the engine holds (a Ray connection)."""

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LocalEngine(Engine):
    """A fork pool over the local cores; one worker runs in-process."""

    name = "local"

    def __init__(self, workers: int | None = None) -> None:
        self.workers = workers or os.cpu_count() or 1

    def map(self, fn: Callable[[Any], Any], jobs: Sequence[Any], *, desc: str = "jobs",
            progress: bool = True, unit: str = "job") -> tuple[list[Any], RunStats]:
        from tqdm import tqdm

        stats = RunStats(self.name, self.workers, len(jobs))
        out: list[Any] = [None] * len(jobs)
        t0 = time.perf_counter()
        with tqdm(total=len(jobs), desc=desc, unit=unit, disable=not progress, leave=False) as bar:
            if self.workers == 1 or len(jobs) <= 1:
                for i, job in enumerate(jobs):
                    out[i], node, seconds = _call(fn, job)
                    stats.add(node, seconds)
                    bar.update(1)
            else:
                with mp.get_context("fork").Pool(min(self.workers, len(jobs))) as pool:
                    for i, res, node, seconds in pool.imap_unordered(
                            _call_indexed, [(fn, i, j) for i, j in enumerate(jobs)]):
                        out[i] = res
                        stats.add(node, seconds)
                        bar.update(1)
        stats.wall_s = time.perf_counter() - t0
        return out, stats


def import_ray() -> Any:
    """`ray`, or a CliError with the one-line install hint."""
    try:
        import ray
    except ImportError:
        raise CliError(RAY_INSTALL_HINT) from None
    return ray


class RayEngine(Engine):
    """One Ray task per job (1 CPU each) on a local Ray instance or a cluster.

    Without `address` a private local instance with `workers` CPUs is started
    (and stopped on close); with one (`auto`, `HOST:PORT` or `ray://...`) the
    engine joins that cluster, and `workers` is the cluster's CPU count.
    Results are fetched in submission order, so they do not depend on which
    node ran which task; `RunStats.nodes` records where each ran.
    """

    name = "ray"

    def __init__(self, workers: int | None = None, address: str | None = None) -> None:
        ray = import_ray()
        self._ray = ray
        self._own = address is None
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                                  "configure_logging": False}
        if self._own:
            kwargs["num_cpus"] = workers or os.cpu_count() or 1
        else:
            kwargs["address"] = address
        try:
            # Workers import the qnav packages from the driver's tree when they run on this machine;
            # cluster workers need qnav installed (docs/campaigns.md).
            ray.init(**kwargs)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            raise CliError(f"cannot reach Ray at {address or 'a local instance'}: "
                           f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
        self.workers = int(ray.cluster_resources().get("CPU", 1)) if not self._own else kwargs["num_cpus"]
        # SPREAD: campaign jobs are CPU-bound and independent; the default (pack the local node first)
        # ran all jobs of a short campaign on one node of a two-node cluster
        self._remote = ray.remote(num_cpus=1, max_retries=2, scheduling_strategy="SPREAD")(_ray_task)

    def map(self, fn: Callable[[Any], Any], jobs: Sequence[Any], *, desc: str = "jobs",
            progress: bool = True, unit: str = "job") -> tuple[list[Any], RunStats]:
        from tqdm import tqdm

        ray = self._ray
        stats = RunStats(self.name, self.workers, len(jobs))
        t0 = time.perf_counter()
        fn_ref = ray.put(fn)
        refs = [self._remote.remote(fn_ref, job) for job in jobs]
        pending = list(refs)
        with tqdm(total=len(jobs), desc=desc, unit=unit, disable=not progress, leave=False) as bar:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                bar.update(len(done))
        out: list[Any] = []
        for res, node, seconds in ray.get(refs):
            out.append(res)
            stats.add(node, seconds)
        stats.wall_s = time.perf_counter() - t0
        return out, stats

    def close(self) -> None:
        if self._ray.is_initialized():
            self._ray.shutdown()


def _ray_task(fn: Callable[[Any], Any], job: Any) -> tuple[Any, str, float]:
    """Runs on a Ray worker: the job, the Ray node id it ran on, its run time."""
    import ray

    t0 = time.perf_counter()
    res = fn(job)
    return res, ray.get_runtime_context().get_node_id(), time.perf_counter() - t0


def make_engine(name: str, workers: int | None = None, address: str | None = None) -> Engine:
    """The engine a command's `--engine/--workers/--ray-address` ask for."""
    if workers is not None and workers < 1:
        raise CliError(f"--workers must be >= 1, got {workers}")
    if name == "local":
        if address:
            raise CliError("--ray-address needs --engine ray")
        return LocalEngine(workers)
    if name == "ray":
        return RayEngine(workers, address)
    raise CliError(f"unknown engine {name!r}: choose from {', '.join(ENGINES)}")


def add_engine_arguments(p: Any, what: str = "jobs", workers: int | None = None,
                         workers_help: str = "parallel workers") -> None:
    """`--engine`, `--workers`, `--ray-address` on a campaign command (`workers`:
    the --workers default, None: all local cores / the cluster's CPUs)."""
    p.add_argument("--engine", choices=ENGINES, default="local",
                   help=f"where the {what} run: a local process pool (default) or Ray "
                        "(pip install 'qnav[cluster]')")
    default = ("all local cores; with --ray-address: the cluster's CPUs" if workers is None else str(workers))
    p.add_argument("--workers", type=int, default=workers, metavar="N", help=f"{workers_help} (default: {default})")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="join a running Ray cluster (auto, HOST:PORT or ray://HOST:10001) instead of "
                        "starting a private one; needs --engine ray")


def engine_from_args(args: Any) -> Engine:
    return make_engine(args.engine, args.workers, args.ray_address)


def campaign_path(json_path: str | os.PathLike[str]) -> str:
    """Where a result file's campaign record goes: FILE.json -> FILE.campaign.json."""
    p = os.fspath(json_path)
    return (p[:-5] if p.endswith(".json") else p) + ".campaign.json"


def write_campaign(json_path: str | None, campaign: dict[str, Any]) -> None:
    """Write the campaign record (engine, workers, nodes, wall times) beside a
    result file, so the result file itself depends only on the seeded jobs."""
    if not json_path:
        return
    import json

    from firmware_py.atomic import atomic_write

    path = campaign_path(json_path)
    atomic_write(path, json.dumps(campaign, indent=1) + "\n")
    print(f"wrote {path}")
