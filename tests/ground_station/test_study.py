"""`qnav study` (ground_station/lab/study.py): bootstrapped CIs, steps to
threshold from the greedy checkpoints, study.json identical on one worker and
on the two-process pool (timings only in campaign.json), the CLI run and its
errors, and `qnav train --recipe`."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ground_station.lab.campaign.engines import LocalEngine
from ground_station.lab.study import bootstrap_ci, run_any_job, run_job, study, tables
from ground_station.learn.config import TrainConfig, recipe_config, recipes

ROOT = Path(__file__).resolve().parents[2]
BASE = TrainConfig.of(map="paper10", targets="A,B,C,D", steps=30_000)


def qnav(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ground_station.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=300, check=False)


def test_bootstrap_ci_brackets_the_mean_and_narrows_with_n():
    rng = np.random.default_rng(1)
    small = rng.normal(10, 2, 10)
    big = rng.normal(10, 2, 400)
    m, lo, hi = bootstrap_ci(small)
    assert lo < m < hi and m == pytest.approx(small.mean())
    m2, lo2, hi2 = bootstrap_ci(big)
    assert hi2 - lo2 < hi - lo
    assert lo2 < 10 < hi2
    assert bootstrap_ci(small) == bootstrap_ci(small)  # seeded resampling: reproducible
    m3, lo3, hi3 = bootstrap_ci(np.stack([small, small + 1]), axis=1)  # per row
    assert m3[1] == pytest.approx(m3[0] + 1) and np.all(lo3 < m3) and np.all(m3 < hi3)
    assert bootstrap_ci([3.0]) == (3.0, 3.0, 3.0)


def test_job_steps_to_threshold_is_the_first_checkpoint_at_or_above_it():
    job = {"group": "lr", "schedule": "decay", "config": BASE.flat(), "eval_every": 1000, "threshold": 0.95}
    r = run_job(job)
    c = r["curve"]
    assert c["steps"] == list(range(1000, 30_001, 1000))
    assert c["episodes"] == sorted(c["episodes"]) and c["episodes"][-1] > 0
    first = next(s for s, v in zip(c["steps"], c["success"], strict=True) if v >= 0.95)
    assert r["steps_to_threshold"] == first
    assert r["final_success"] == c["success"][-1]
    assert c["qmax"][-1] > c["qmax"][0]  # values grow toward the goal reward, as in the paper's Fig. 5
    never = run_job({**job, "threshold": 1.0, "config":
        TrainConfig.of(map="paper10", targets="A,B,C,D", steps=2000).flat()})
    assert never["steps_to_threshold"] is None


def test_study_json_is_the_same_on_one_worker_and_on_the_pool():
    kw = {"constant_epsilon": 0.1, "learners": ["q", "sarsa", "double-q"], "learner_lrs": [0.5],
          "eval_every": 2000}
    a = study(BASE, [0.3, 0.9], 3, engine=LocalEngine(1), **kw)
    b = study(BASE, [0.3, 0.9], 3, engine=LocalEngine(2), **kw)
    ca, cb = a.pop("campaign"), b.pop("campaign")
    assert json.dumps(a) == json.dumps(b)
    assert ca["workers"] == 1 and cb["workers"] == 2 and "learner_train_seconds" in ca
    assert len(a["runs"]) == 2 * 2 * 3 + 3 * 3
    assert "bootstrapped 95 % CI" in a["ci"] and "bootstrapped 95 % CI" in tables({**a, "campaign": ca})
    rows = {(r["schedule"], r["lr"]): r for r in a["lr_study"]}
    assert rows[("decay", 0.9)]["steps_to_threshold"]["mean"] < rows[("decay", 0.3)]["steps_to_threshold"]["mean"]
    assert a["optimum"]["success"] == 1.0 and a["optimum"]["path_ratio_mean"] == 1.0
    ex = a["optimum"]["example"]
    assert len(ex["bfs_path"]) == ex["bfs_steps"] + 1 and len(ex["greedy_path"]) == ex["greedy_steps"] + 1


def test_cli_study_writes_json_png_and_campaign(tmp_path):
    p = qnav("study", "--out", str(tmp_path), "--seeds", "2", "--lrs", "0.5", "--learners", "q,dyna-q",
             "--learner-lrs", "0.5", "--steps", "10000", "--eval-every", "2000", "--sector-seeds", "2",
             "--sector-learners", "q,q-lambda", "--sector-steps", "100000", "--sector-eval-every", "50000",
             "--sector-sample", "100")
    assert p.returncode == 0, p.stderr
    assert "bootstrapped 95 % CI" in p.stdout and "| q-lambda |" in p.stdout and "path / any-angle" in p.stdout
    data = json.loads((tmp_path / "study.json").read_text())
    assert "campaign" not in data and "train_seconds" not in json.dumps(data)
    assert [r["learner"] for r in data["sector"]["rows"]] == ["q", "q-lambda"]
    assert data["sector"]["config"]["steps"] == 100_000 and data["sector"]["config"]["encoding"] == "sector"
    camp = json.loads((tmp_path / "campaign.json").read_text())
    assert camp["jobs"] == 2 * 2 + 2 * 2 + 2 * 2 and "bfs_all_pairs_s" in camp["optimum"]
    assert set(camp["sector_train_seconds"]) == {"q", "q-lambda"}
    assert (tmp_path / "study.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("args,text", [
    ("--learners q,td0", "unknown learner"),
    ("--sector-learners sarsa,td1", "--sector-learners: unknown learner"),
    ("--sector-seeds -1", "--sector-seeds"),
    ("--seeds 0", "--seeds"),
    ("--lrs 0", "learning rates"),
    ("--map nosuchmap", "nosuchmap"),
    ("--map maze-15x15-s2 --targets ''", "defines no targets"),
    ("--targets A,Z", "Z"),
])
def test_cli_study_bad_input_is_one_line(tmp_path, args, text):
    p = qnav("study", "--out", str(tmp_path), *shlex.split(args))  # the shell's words: '' is an empty argument
    assert p.returncode == 2 and text in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr


@pytest.mark.parametrize("args,text", [
    (["--map", "maze-15x15-s2"], "defines no targets"),  # was a worker's traceback
    (["--targets", "A,Z"], "Z"),
])
def test_cli_sweep_bad_map_targets_are_one_line(tmp_path, args, text):
    p = qnav("sweep", "--out", str(tmp_path), "--lrs", "0.5", "--seeds", "1", "--steps", "1000", *args)
    assert p.returncode == 2 and text in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr


def test_recipes_are_the_train_defaults(tmp_path):
    assert recipe_config("sector", {}).steps == 20_000_000 and recipe_config("sector", {}).reward_step == 0.0
    assert recipe_config("cell", {}) == TrainConfig.of()
    assert recipe_config("sector", {"lr": 0.3}).lr == 0.3  # given flags win
    assert set(recipes()) == {"cell", "sector", "sector-memory"}
    p = qnav("train", "--recipe", "shipped-cell", "--steps", "20000", "--out", str(tmp_path / "c"), "--quiet")
    assert p.returncode == 0, p.stderr
    meta = json.loads((tmp_path / "c" / "meta.json").read_text())
    assert meta["encoding"] == "cell" and meta["config"]["lr"] == 0.5 and meta["config"]["steps"] == 20000
    # the sector recipe is both --recipe shipped-sector and the CLI defaults of --encoding sector
    for name, argv in (("r", ["--recipe", "shipped-sector"]), ("e", ["--encoding", "sector"])):
        p = qnav("train", *argv, "--steps", "1000", "--out", str(tmp_path / name), "--quiet")
        assert p.returncode == 0, p.stderr
        cfg = json.loads((tmp_path / name / "meta.json").read_text())["config"]
        assert cfg["encoding"] == "sector" and cfg["steps"] == 1000
        assert {k: cfg[k] for k in recipes()["sector"] if k != "steps"} == \
            {k: v for k, v in recipes()["sector"].items() if k != "steps"}
    p = qnav("train", "--recipe", "shipped-sector", "--encoding", "cell", "--out", str(tmp_path / "x"))
    assert p.returncode == 2 and "trains the sector encoding" in p.stderr


def test_sector_job_checkpoints_and_path_ratios():
    from ground_station.lab.study import SectorEval, sector_base, sector_jobs
    from ground_station.learn.sector.kernels import SUCCESS
    from ground_station.learn.sector.trainer import SectorTrainer, sector_encoder
    from ground_station.maps import load_map

    sbase = sector_base(BASE, 400_000)
    assert (sbase.encoding, sbase.steps, sbase.lr) == ("sector", 400_000, recipes()["sector"]["lr"])
    jobs = sector_jobs(sbase, ["q", "expected-sarsa"], 2, 200_000, 0.5, 300)
    assert [(j["config"]["learner"], j["config"]["seed"]) for j in jobs] == [
        ("q", 0), ("q", 1), ("expected-sarsa", 0), ("expected-sarsa", 1)]
    r = run_any_job(jobs[2])
    assert r["curve"]["steps"] == [200_000, 400_000] and r["final_success"] == r["curve"]["success"][-1]
    first = next((s for s, v in zip(r["curve"]["steps"], r["curve"]["success"], strict=True) if v >= 0.5), None)
    assert r["steps_to_threshold"] == first and r["learner"] == "expected-sarsa"
    assert r == {**run_any_job(jobs[2]), "train_seconds": r["train_seconds"]}  # seeded: the same run
    # every success drives at least the disc's any-angle optimum (to within the goal tolerance)
    # and often less than the 8-connected grid path
    gm = load_map("paper10")
    cfg = TrainConfig.of(**jobs[0]["config"])
    tr = SectorTrainer([gm], cfg, sector_encoder(cfg))
    q = np.zeros((tr.n_states, tr.n_actions))
    tr.run(q, 0, cfg.steps)
    ev = SectorEval(gm, cfg, 300)
    outcome, path = ev.rollouts(q, tr.encoder)
    ok = outcome == SUCCESS
    assert ok.mean() > 0.3
    assert np.all(path[ok] / ev.anyangle[ok] >= 0.995)
    assert np.mean(path[ok] < ev.octile[ok]) > 0.5


class _Stop(Exception):
    """Raised by the stand-in campaign runner once the command has built its config."""


@pytest.mark.parametrize("command, module, runner", [("sweep", "ground_station.lab.sweep", "sweep"),
                                                      ("study", "ground_station.lab.study", "study")])
def test_sweep_and_study_take_the_recipe_of_their_encoding_like_train(monkeypatch, tmp_path, command, module, runner):
    """`qnav sweep --encoding sector` used to train with the cell defaults (3M steps,
    reward_step -0.01, epsilon_end 0.1) where `qnav train --encoding sector` takes
    the sector recipe; a flag given still wins. The command runs as parsed, up to
    the campaign, whose runner here only records the config it is handed."""
    import importlib

    from ground_station import cli

    seen = []

    def record(cfg, *a, **kw):
        seen.append(cfg)
        raise _Stop

    monkeypatch.setattr(importlib.import_module(module), runner, record)
    if command == "sweep":
        argv = ["sweep", "--out", str(tmp_path), "--encoding", "sector", "--lrs", "0.2", "--seeds", "1",
                "--workers", "1"]
        with pytest.raises(_Stop):
            cli.main(argv)
        with pytest.raises(_Stop):
            cli.main([*argv, "--steps", "5000", "--epsilon-end", "0.2"])
        (recipe, given) = seen
        want = {k: v for k, v in recipes()["sector"].items() if k != "lr"}  # sweep sets lr per run
        assert {k: getattr(recipe, k) for k in want} == want and recipe.encoding == "sector"
        assert (given.steps, given.epsilon_end, given.reward_step) == (5000, 0.2, recipes()["sector"]["reward_step"])
    else:  # a cell study: the cell recipe is the defaults, the study's own steps default stays
        with pytest.raises(_Stop):
            cli.main(["study", "--out", str(tmp_path), "--seeds", "1", "--lrs", "0.5", "--learners", "q",
                      "--workers", "1"])
        (cfg,) = seen
        assert cfg.encoding == "cell" and cfg.steps == 100_000 and cfg.lr == TrainConfig.of().lr
