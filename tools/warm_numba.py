"""Fill numba's on-disk cache (`cache=True` kernels, in `ground_station.jitcache`'s folder) once,
before the test suite runs.

Why: on a fresh clone nothing is compiled, and the suite's pytest-xdist workers
and the `qnav` processes its tests start each compile the same training,
evaluation, twin and planner kernels while none is cached yet (measured: the
`qnav bench train` test took 32-42 s cold and 1.9 s warm). Running
the station's commands at toy sizes compiles each kernel once, with the
argument types the commands use, and every later process loads it (two processes
side by side: see main).

`make test` runs this in the background beside ruff, mypy and the Debian test
packages, then waits for it before pytest. It is not a test: it checks
nothing but exits non-zero (with the failing command named) if a command fails.

    python tools/warm_numba.py [--quiet]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import multiprocessing
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def commands(out: Path) -> list[list[str]]:
    """`qnav` argv lists that between them call every cached kernel family."""
    return [
        # training kernels of every shipped encoding (cell, sector, sector-memory)
        ["bench", "train", "--steps", "20000", "--baseline-seconds", "0.05", "--sector-steps", "2000",
         "--json", str(out / "bench_train.json")],
        # greedy evaluation kernels per encoding
        ["train", "--map", "paper10", "--encoding", "cell", "--targets", "A,B", "--steps", "20000",
         "--out", str(out / "cell"), "--quiet"],
        ["eval", str(out / "cell"), "--json"],
        ["train", "--map", "paper10", "--encoding", "sector", "--steps", "2000", "--out", str(out / "sector"),
         "--quiet"],
        ["eval", str(out / "sector"), "--sample", "4", "--json"],
        ["train", "--map", "paper10", "--encoding", "sector-memory", "--steps", "2000",
         "--out", str(out / "sector_memory"), "--quiet"],
        ["eval", str(out / "sector_memory"), "--sample", "4", "--json"],
        # the learners of the study (SARSA, Expected SARSA, Double Q, Dyna-Q, Q(lambda)), BFS optimum
        ["study", "--out", str(out / "study"), "--lrs", "0.5:0.5:0.1", "--seeds", "1", "--steps", "3000",
         "--eval-every", "1000", "--learner-lrs", "0.5", "--workers", "1"],
        # the twin's rollouts with discs and movers, the scenario sampler, the baselines
        ["bench", "nav", "--map", "paper10", "--episodes", "2", "--workers", "1",
         "--json", str(out / "bench_nav.json")],
        # the privileged planner of `bench ceiling` (lab/nav/oracle.py: 11 s to compile; each xdist worker
        # running a tests/ground_station/test_oracle.py test compiled it anew while none was cached)
        ["bench", "ceiling", "--map", "paper10", "--episodes", "2", "--controllers", "", "--workers", "1"],
    ]


def warm_python_callers() -> None:
    """Kernels the station calls from Python, not from another kernel (a kernel called inside one is
    compiled into it, not cached on its own), so no command above compiles them: the Gymnasium env's
    steps, the re-planner's expected readings, the planner's and the any-angle optimum's segment tests
    (measured: a fresh clone's suite compiled ~25 kernels warm_numba had not, these among them, often
    in several pytest-xdist workers at once; the rest are kernels tests call directly)."""
    import numpy as np

    from firmware_py import robot_spec
    from ground_station.lab.anyangle import anyangle_distances
    from ground_station.learn.envs.sector_env import SectorNavEnv
    from ground_station.maps import load_map
    from ground_station.maps.planner import plan_waypoints
    from ground_station.nav.replan import UnmappedPoints

    gm = load_map("paper10")
    for guidance in ("path", "direct"):
        env = SectorNavEnv(gm, goal="A", guidance=guidance)
        env.reset(seed=0)
        rng = np.random.default_rng(0)
        for _ in range(20):
            if env.step(int(rng.integers(4)))[2]:  # terminated: a new episode, as Gymnasium asks
                env.reset()
    UnmappedPoints(gm).observe(0, 1250.0, 1250.0, 0.0, [300] * robot_spec.SENSOR_COUNT)
    anyangle_distances(gm, float(robot_spec.ROBOT_RADIUS_MM))
    for radius in (robot_spec.ROBOT_RADIUS_MM, float(robot_spec.ROBOT_RADIUS_MM)):  # a profile's int, the default
        plan_waypoints(gm, gm.targets["A"], gm.targets["D"], radius_mm=radius)


def _run(argvs: list[list[str]], out: Path, quiet: bool) -> int:
    """Run `qnav` argv lists in order in this process; 1 (naming the command) on the first failure."""
    from ground_station import cli

    for argv_ in argvs:
        t0 = time.monotonic()
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
            try:
                code = cli.main(argv_)
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 1
        if code != 0:
            print(f"warm_numba: qnav {' '.join(argv_)} failed (exit {code}):\n{buf.getvalue()[-2000:]}",
                  file=sys.stderr)
            return 1
        if not quiet:
            print(f"warm_numba: qnav {argv_[0]} {argv_[1]}: {time.monotonic() - t0:.1f} s", flush=True)
    return 0


def _run_side(argvs: list[list[str]], out: Path, quiet: bool) -> int:
    """The second process's share: its commands, then the kernels called from Python."""
    code = _run(argvs, out, quiet)
    t0 = time.monotonic()
    try:
        warm_python_callers()
    except Exception as exc:  # noqa: BLE001 - named on one line like a failing command
        print(f"warm_numba: kernels called from Python failed: {exc!r}", file=sys.stderr)
        return 1
    if not quiet:
        print(f"warm_numba: kernels called from Python: {time.monotonic() - t0:.1f} s", flush=True)
    return code


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quiet", action="store_true", help="print only failures")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))

    t_all = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="qnav-warm-") as tmp:
        # two processes on two cores: the training and evaluation commands in one, the study
        # and the twin bench (kernels of their own: learners, BFS, scenarios, baselines) in
        # the other, so the second's wall time hides inside the first's; numba writes its
        # cache files atomically. `make test` waits on this before pytest.
        argvs = commands(Path(tmp))
        side = [a for a in argvs if a[:1] == ["study"] or a[:2] in (["bench", "nav"], ["bench", "ceiling"])]
        main_line = [a for a in argvs if a not in side]
        ctx = multiprocessing.get_context("fork")
        with ctx.Pool(2) as pool:
            main_run = pool.apply_async(_run, (main_line, Path(tmp), args.quiet))
            side_run = pool.apply_async(_run_side, (side, Path(tmp), args.quiet))
            codes = [main_run.get(), side_run.get()]
    if not args.quiet:
        print(f"warm_numba: numba cache filled in {time.monotonic() - t_all:.1f} s")
    return max(codes)


if __name__ == "__main__":
    raise SystemExit(main())
