"""The campaign layer: search spaces, the local engine, and the same seeded
campaigns on the local pool and on a two-node Ray cluster (head + worker node
started as separate `ray start` processes on this machine)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ground_station.errors import CliError
from ground_station.lab.campaign import engines, space

ROOT = Path(__file__).resolve().parents[2]
SWEEP = ["sweep", "--map", "paper10", "--encoding", "cell", "--lrs", "0.2,0.4,0.6", "--seeds", "1",
         "--steps", "20000", "--curve-points", "20", "--no-curves"]  # the curves are study jobs: test_train


def qnav(*args: str, env: dict | None = None, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ground_station.cli", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)


# --- search spaces --------------------------------------------------------------------

def test_space_grid_and_seeded_samples():
    axes = [space.parse_axis("gamma=grid:0.9,0.95"), space.parse_axis("epsilon_end=uniform:0.05,0.2"),
            space.parse_axis("max-episode-steps=int:50,80")]
    pts = space.points(axes, samples=3, seed=5)
    assert len(pts) == 6
    assert {p["gamma"] for p in pts} == {0.9, 0.95}
    assert all(0.05 <= p["epsilon_end"] <= 0.2 and 50 <= p["max_episode_steps"] <= 80 for p in pts)
    assert pts == space.points(axes, samples=3, seed=5)          # seeded: the same draws every time
    assert pts != space.points(axes, samples=3, seed=6)
    assert isinstance(pts[0]["max_episode_steps"], int)


@pytest.mark.parametrize("spec, msg", [
    ("gamma", "FIELD=KIND:VALUES"), ("nope=grid:1", "no field 'nope'"), ("gamma=grid:abc", "not a valid"),
    ("lr=uniform:0.5", "LO,HI"), ("lr=loguniform:0,1", "0 < LO < HI"), ("lr=bell:1,2", "unknown kind"),
    ("seed=grid:1,2", "--seeds"), ("gamma=grid:nan", "not a valid"),
])
def test_space_bad_specs(spec, msg):
    with pytest.raises(ValueError, match=msg):
        space.parse_axis(spec)


# --- engines --------------------------------------------------------------------------

def _slow_square(x: int) -> int:
    time.sleep(0.05 * (4 - x % 4))  # later jobs finish first
    return x * x


def test_local_engine_keeps_job_order_and_counts():
    out, stats = engines.LocalEngine(2).map(_slow_square, list(range(8)), progress=False)
    assert out == [x * x for x in range(8)]
    assert stats.jobs == 8 and sum(stats.nodes.values()) == 8 and stats.workers == 2


def test_engine_arguments_refused_with_one_line(tmp_path):
    with pytest.raises(CliError, match="--workers must be >= 1"):
        engines.make_engine("local", 0)
    with pytest.raises(CliError, match="needs --engine ray"):
        engines.make_engine("local", 1, "127.0.0.1:1")
    r = qnav(*SWEEP, "--out", str(tmp_path / "x"), "--tune")
    assert r.returncode != 0 and "--tune needs --engine ray" in r.stderr
    assert not (tmp_path / "x").exists()


def test_bench_campaign_takes_the_shared_engine_arguments():
    """The same --engine/--workers/--ray-address actions as sweep and study; its own --workers default (2)."""
    from ground_station.cli import build_parser

    def option(argv, dest):
        parser = build_parser()
        sub = parser._subparsers._group_actions[0].choices[argv[0]]
        if argv[0] == "bench":
            sub = sub._subparsers._group_actions[0].choices[argv[1]]
        return next(a for a in sub._actions if a.dest == dest)

    for dest in ("engine", "ray_address"):
        assert option(["bench", "campaign"], dest).help.replace("twin runs", "X") == \
            option(["sweep"], dest).help.replace("training runs", "X")
    workers = option(["bench", "campaign"], "workers")
    assert workers.default == 2 and "(default: 2)" in workers.help


def test_ray_missing_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # what `import ray` sees without the extra
    with pytest.raises(CliError, match=r"pip install 'qnav\[cluster\]'"):
        engines.make_engine("ray", 1)


def test_campaign_path():
    assert engines.campaign_path("out/hil.json") == "out/hil.campaign.json"
    assert engines.campaign_path("res") == "res.campaign.json"


# --- the same campaigns on the local pool and on a Ray cluster ------------------------

# module scope: `--dist loadgroup` sends the "ray" group to one worker as one unit, so its tests run
# one after another and the cluster stops after the last of them (a session-scoped one idled beside the
# rest of the run and stopped at its very end, the run's tail); Ray processes that ignore SIGTERM for
# 3 s are killed (waiting 10 s for them was the whole of that stop)
@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    pytest.importorskip("ray", reason="Ray (qnav[cluster]) is not installed: the Ray engine cannot run")
    from ground_station.lab.rigs.ray_cluster import LocalRayCluster

    c = LocalRayCluster(tmp_path_factory.mktemp("raycluster"), workers=1)
    try:
        c.start()
    except BaseException:
        c.stop()
        raise
    yield c
    c.stop(timeout_s=3.0)
    assert c.pids() == [], "Ray processes left running"


@pytest.fixture(scope="session")
def local_sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep_local")
    r = qnav(*SWEEP, "--out", str(out), "--workers", "2")
    assert r.returncode == 0, r.stderr
    return out


# one bench with both kinds of job: the twin's episodes (pure compute) and HIL episodes (each starts a
# hub, qnav-sim and qnav-robot in the pool's worker or on the Ray worker that runs it); its local run at
# one worker is the reference both tests below compare with (same worker: the "ray" group), so the
# suite runs it once; 2 controllers x ceil(5 / 3) twin jobs spread over both of the cluster's nodes
BENCH = ["bench", "nav", "--map", "maze-16x16-s1", "--episodes", "5", "--hil", "--hil-episodes", "1",
         "--controllers", "learnt,vfh"]


@pytest.fixture(scope="module")
def local_bench(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_local") / "one.json"
    one = qnav(*BENCH, "--workers", "1", "--batch", "7", "--json", str(out))
    assert one.returncode == 0, one.stderr[-2000:]
    return out


@pytest.mark.xdist_group("ray")  # beside the Ray tests: they share its local reference
def test_bench_nav_result_independent_of_workers_and_batches(local_bench, tmp_path):
    two = qnav(*BENCH, "--workers", "2", "--batch", "3", "--json", str(tmp_path / "two.json"))
    assert two.returncode == 0, two.stderr[-2000:]
    assert (tmp_path / "two.json").read_bytes() == local_bench.read_bytes()
    camp = json.loads((tmp_path / "two.campaign.json").read_text())
    assert camp["twin"]["jobs"] == 2 * 2 and camp["twin"]["workers"] == 2  # 2 controllers x ceil(5 / 3)
    assert "hil" in camp  # the HIL episodes went through the pool too


@pytest.mark.ray
@pytest.mark.xdist_group("ray")  # one worker owns the module's cluster
@pytest.mark.timeout(420)  # a run: 22 s (+ 33 s cluster start) in a quiet fresh-clone make test, 92 s (+ 33 s) beside two busy loops; up to three
def test_bench_identical_on_ray_cluster(cluster, local_bench, tmp_path):
    # Ray hands a task queue on to the worker it already leased (the owner reuses the lease while
    # tasks of the same kind wait), so the twin's four short jobs went 3 + 1 over the two nodes in 8
    # of 8 runs here, and once in a loaded make test all four ran on one (the second node's lease
    # came after the first had drained the queue). Every run must equal the local one; the second
    # node must have run jobs in one of up to three.
    runs = []
    for attempt in range(3):
        out = tmp_path / f"ray{attempt}.json"
        on_ray = qnav(*BENCH, "--batch", "3", "--json", str(out), "--engine", "ray",
                      "--ray-address", cluster.address, env=cluster.env())
        assert on_ray.returncode == 0, on_ray.stderr[-2000:]
        assert out.read_bytes() == local_bench.read_bytes()
        camp = json.loads((tmp_path / f"ray{attempt}.campaign.json").read_text())
        assert camp["twin"]["engine"] == "ray" and camp["hil"]["engine"] == "ray" and camp["hil"]["jobs"] >= 1, camp
        assert json.loads(out.read_text())["hil"]  # HIL outcomes are in the result compared above
        runs.append(camp["twin"]["nodes"])
        if len(camp["twin"]["nodes"]) == 2:
            break
    assert len(runs[-1]) == 2, runs


@pytest.mark.ray
@pytest.mark.xdist_group("ray")  # one worker owns the module's cluster
@pytest.mark.timeout(300)  # two Tune runs: 20 s alone, 21 s beside two busy loops (155 s with Ray's workers at nice 15)
def test_tune_sweep_resumes_after_interruption(cluster, local_sweep, tmp_path):
    """Interrupt a Tune sweep once its first trial has finished, run the same
    command again: it restores the experiment and the result equals the local
    engine's."""
    cmd = [sys.executable, "-m", "ground_station.cli", *SWEEP, "--out", str(tmp_path), "--engine", "ray",
           "--ray-address", cluster.address, "--tune"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=cluster.env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and proc.poll() is None:
            if any(p.stat().st_size > 0 for p in (tmp_path / "tune").glob("sweep/job_*/result.json")):
                break
            time.sleep(0.2)
        interrupted = proc.poll() is None
        if interrupted:
            os.killpg(proc.pid, signal.SIGINT)
        proc.wait(timeout=60)
        assert interrupted, "the sweep finished before it could be interrupted"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert (tmp_path / "tune" / "sweep").is_dir()
    r = qnav(*SWEEP, "--out", str(tmp_path), "--engine", "ray", "--ray-address", cluster.address, "--tune",
             env=cluster.env())
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "sweep.json").read_bytes() == (local_sweep / "sweep.json").read_bytes()
    assert json.loads((tmp_path / "campaign.json").read_text())["engine"] == "ray-tune"


def test_ray_is_imported_only_when_asked_for():
    code = ("import sys; from ground_station.cli import build_parser; build_parser(); "
            "from ground_station.lab.campaign import engines, space; from ground_station.lab import sweep; "
            "from ground_station.lab.bench import hil, campaign; print('ray' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60, check=False)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "False"
