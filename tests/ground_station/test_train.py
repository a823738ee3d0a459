"""Q-learning trainer: the update against hand-computed values, the kernel's
fixed point on a corridor, reproducibility, evaluation outcomes, and the
CLI run folder contract (subprocess smoke tests)."""

import json
import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_py.kinds.cell.encoder import CellEncoder
from ground_station.learn.cell.evaluate import (
    COLLISION,
    LOOP,
    POLICY_NEAREST,
    SUCCESS,
    evaluate_cell,
    rollouts_cell,
)
from ground_station.learn.cell.trainer import cell_state, q_update, train_cell
from ground_station.learn.envs.cell_env import cell_transitions
from ground_station.learn.train import TrainConfig, learning_curve, train
from ground_station.maps import GridMap, load_map, parse_map

UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3


def corridor(n: int) -> GridMap:
    occ = parse_map(f"type octile\nheight 1\nwidth {n}\nmap\n{'.' * n}\n").occ
    return GridMap(f"corridor{n}", occ, {"G": (n - 1, 0)})


def test_q_update_on_a_three_state_chain_by_hand():
    # states 0 -> 1 -> 2 (terminal goal), action RIGHT; lr 0.5, gamma 0.9
    q = np.zeros((3, 4))
    q_update(q, 0, RIGHT, -0.01, 1, False, 0.5, 0.9)
    assert q[0, RIGHT] == pytest.approx(-0.005)  # 0.5 * (-0.01 + 0.9*0 - 0)
    q_update(q, 1, RIGHT, 1.0, 2, True, 0.5, 0.9)
    assert q[1, RIGHT] == pytest.approx(0.5)  # terminal: no bootstrap
    q_update(q, 0, RIGHT, -0.01, 1, False, 0.5, 0.9)
    assert q[0, RIGHT] == pytest.approx(0.2175)  # -0.005 + 0.5 * (-0.01 + 0.9*0.5 + 0.005)
    q[2, :] = 7.0  # a terminal transition must ignore the next state's values
    q_update(q, 1, UP, -1.0, 2, True, 0.5, 0.9)
    assert q[1, UP] == pytest.approx(-0.5)
    assert q[0, LEFT] == 0 and q[0, UP] == 0


def test_kernel_converges_to_hand_computed_q_star_on_a_corridor():
    # deterministic world + lr 1: every visited (s, a) holds its exact Q* value
    cfg = TrainConfig.of(map="corridor", steps=20_000, lr=1.0, gamma=0.9, epsilon_start=1.0,
                      epsilon_end=1.0, reward_goal=1.0, reward_step=-0.1, reward_collision=-1.0)
    q = train(cfg, corridor(3)).q  # cells 0, 1, goal 2
    assert q[1, RIGHT] == pytest.approx(1.0)
    assert q[0, RIGHT] == pytest.approx(-0.1 + 0.9 * 1.0)
    assert q[1, LEFT] == pytest.approx(-0.1 + 0.9 * 0.8)
    assert q[0, LEFT] == pytest.approx(-1.0)  # off the map: collision, terminal
    assert q[0, UP] == pytest.approx(-1.0) and q[1, DOWN] == pytest.approx(-1.0)
    assert (q[2] == 0).all()  # the goal state is never updated


def test_same_seed_same_table_regardless_of_chunking():
    cfg = TrainConfig.of(steps=200_000, seed=5)
    gm = load_map("paper10")
    a = train_cell(cfg, gm)
    b = train_cell(replace(cfg, chunk_steps=7_777), gm)
    assert np.array_equal(a.q, b.q)
    assert np.array_equal(a.returns, b.returns) and np.array_equal(a.successes, b.successes)
    c = train_cell(replace(cfg, seed=6), gm)
    assert not np.array_equal(a.q, c.q)


def test_paper10_all_targets_optimal_after_training():
    gm = load_map("paper10")
    res = train_cell(TrainConfig.of(steps=1_000_000), gm)
    assert res.q.shape == (400, 4)
    goals = [tuple(g) for g in res.meta["goals"]]
    rep = evaluate_cell(res.q, gm, goals)
    assert rep["episodes"] == 4 * (len(gm.free_cells()) - 1)
    assert rep["success_rate"] == 1.0
    assert rep["path_ratio_max"] == 1.0
    assert rep["loops"] == rep["collisions"] == rep["timeouts"] == 0
    assert rep["baseline_success_rate"] < 1.0  # paper10 has traps for the greedy baseline
    assert res.successes[-1000:].mean() > res.successes[:1000].mean()  # it learned


def test_rollouts_detect_loops_and_collisions():
    gm = corridor(4)
    nxt = cell_transitions(gm.occ)
    q = np.zeros((4, 4))
    q[1, RIGHT] = q[2, LEFT] = 1.0  # 1 <-> 2 forever
    q[0, UP] = 1.0  # 0: off the map
    goal = np.array([3], dtype=np.int64)
    out, steps = rollouts_cell(q, nxt, 4, goal, np.zeros(3, np.int64), np.array([0, 1, 2], np.int64), 50, 0)
    assert list(out) == [COLLISION, LOOP, LOOP]
    assert steps[1] == 2  # 1 -> 2 -> 1 detected at the first revisit


def test_nearest_neighbour_baseline_loops_in_a_u_trap():
    text = "type octile\nheight 5\nwidth 5\nmap\n.....\n.@@@.\n.@.@.\n.....\n.....\n"
    gm = GridMap("u", parse_map(text).occ, {"G": (2, 0)})
    nxt = cell_transitions(gm.occ)
    out, _ = rollouts_cell(np.zeros((25, 4)), nxt, 5, np.array([2], np.int64),
                           np.zeros(2, np.int64), np.array([2 * 5 + 2, 4 * 5 + 0], np.int64), 50, POLICY_NEAREST)
    assert list(out) == [LOOP, SUCCESS]  # inside the U it cannot back out


def test_evaluate_rejects_a_table_of_the_wrong_shape():
    gm = load_map("paper10")
    with pytest.raises(ValueError, match="does not fit"):
        evaluate_cell(np.zeros((100, 4)), gm, [(2, 2), (9, 0)])


def test_learning_curve_windows():
    rows = learning_curve(np.arange(10.0), np.array([0, 1] * 5, dtype=bool), points=5)
    assert [r["episode"] for r in rows] == [2, 4, 6, 8, 10]
    assert rows[0]["avg_return"] == 0.5 and rows[0]["success_rate"] == 0.5


def qnav(*args, check=True):
    # the installed console script, as a user runs it
    return subprocess.run([str(Path(sys.executable).parent / "qnav"), *args],
                          capture_output=True, text=True, timeout=110, check=check)


def test_cli_train_then_eval_smoke(tmp_path):
    out = tmp_path / "run"
    qnav("train", "--map", "paper10", "--encoding", "cell", "--targets", "A,C", "--steps", "300000",
         "--lr", "0.7", "--gamma", "0.9", "--epsilon", "0.2", "--seed", "3", "--out", str(out), "--quiet")
    q = np.load(out / "q.npy")
    assert q.dtype == np.float64 and q.shape == (200, 4)
    meta = json.loads((out / "meta.json").read_text())
    for key in ("encoding", "encoder", "map", "targets", "goals", "config", "steps", "train_seconds", "created"):
        assert key in meta
    assert meta["encoding"] == "cell" and meta["targets"] == ["A", "C"] and meta["goals"] == [[2, 2], [0, 9]]
    assert meta["encoder"] == {"width": 10, "height": 10, "n_goals": 2, "kind": "cell"}
    assert meta["config"]["lr"] == 0.7 and meta["config"]["epsilon_end"] == 0.2 and meta["steps"] == 300000
    assert set(meta["config"]) == set(TrainConfig.of().flat()) and "targets" in meta["config"]  # every hyperparameter recorded
    assert (out / "metrics.csv").read_text().startswith("episode,avg_return,success_rate\n")
    assert (out / "learning_curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rep = json.loads(qnav("eval", str(out), "--map", "paper10", "--json").stdout)
    for key in ("success_rate", "path_ratio_mean", "path_ratio_max", "timeouts", "collisions", "loops",
                "episodes", "baseline_success_rate"):
        assert key in rep
    assert rep["episodes"] == 2 * 74 and rep["success_rate"] == 1.0


def test_cli_errors_are_one_line_exit_2(tmp_path):
    r = qnav("train", "--map", "nosuchmap", "--out", str(tmp_path / "x"), check=False)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "unknown map 'nosuchmap'" in r.stderr
    r = qnav("train", "--targets", "Q", "--out", str(tmp_path / "x"), check=False)
    assert r.returncode == 2 and "no target 'Q'" in r.stderr
    r = qnav("train", "--lr", "1.5", "--out", str(tmp_path / "x"), check=False)
    assert r.returncode == 2 and "lr must be in (0, 1]" in r.stderr
    r = qnav("train", "--encoding", "sector", "--sector-hold-max", "0", "--out", str(tmp_path / "x"), check=False)
    assert r.returncode == 2 and "sector_hold_max must be >= 1, got 0" in r.stderr
    r = qnav("eval", str(tmp_path), "--map", "paper10", check=False)
    assert r.returncode == 2 and "missing meta.json" in r.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_cli_sweep_smoke(tmp_path):
    qnav("sweep", "--map", "paper10", "--encoding", "cell", "--lrs", "0.2:0.6:0.4", "--seeds", "2",
         "--steps", "20000", "--out", str(tmp_path))
    data = json.loads((tmp_path / "sweep.json").read_text())
    assert data["lrs"] == [0.2, 0.6] and len(data["runs"]) == 4
    assert {r["seed"] for r in data["runs"]} == {0, 1}
    assert (tmp_path / "sweep.png").read_bytes()[:4] == b"\x89PNG"
    curves = json.loads((tmp_path / "curves.json").read_text())  # cell: steps to threshold and Fig. 5, with CIs
    assert curves["seeds"] == 2 and curves["threshold"] == 0.95
    rows = {(r["schedule"], r["lr"]): r for r in curves["lr_study"]}
    assert set(rows) == {(s, lr) for s in ("decay", "constant") for lr in (0.2, 0.6)}
    for r in rows.values():
        lo, hi = r["steps_to_threshold"]["ci95"]
        assert lo <= r["steps_to_threshold"]["mean"] <= hi <= 20000
        assert len(r["curve"]["qmax"]["mean"]) == len(r["curve"]["episodes"]) > 2
        assert r["curve"]["qmax"]["mean"][-1] > r["curve"]["qmax"]["mean"][0]  # values grow as learning goes
    # the larger rate reaches 95 % greedy success sooner (paper's question), with either schedule
    for sched in ("decay", "constant"):
        assert rows[(sched, 0.6)]["steps_to_threshold"]["mean"] < rows[(sched, 0.2)]["steps_to_threshold"]["mean"]
    assert (tmp_path / "curves.png").read_bytes()[:4] == b"\x89PNG"
    qnav("sweep", "--map", "paper10", "--encoding", "cell", "--lrs", "0.5", "--seeds", "1", "--steps", "5000",
         "--no-curves", "--out", str(tmp_path / "bare"))
    assert not (tmp_path / "bare" / "curves.json").exists()


def test_cli_eval_plot_writes_a_png(tmp_path):
    out = tmp_path / "run"
    qnav("train", "--steps", "20000", "--targets", "B", "--out", str(out), "--quiet")
    r = qnav("eval", str(out), "--map", "paper10", "--plot", str(out / "policy.png"))
    assert "success_rate" in r.stdout
    assert (out / "policy.png").read_bytes()[:4] == b"\x89PNG"


@settings(max_examples=300, deadline=None)
@given(w=st.integers(1, 64), h=st.integers(1, 64), n_goals=st.integers(1, 8), data=st.data())
def test_jitted_cell_state_equals_reference_encoder(w, h, n_goals, data):
    col = data.draw(st.integers(0, w - 1))
    row = data.draw(st.integers(0, h - 1))
    g = data.draw(st.integers(0, n_goals - 1))
    assert cell_state(g, row * w + col, w * h) == CellEncoder(w, h, n_goals).encode(col, row, g)


@pytest.mark.parametrize(("encoding", "shown", "hidden"), [
    ("cell", ["--targets", "--learner-lambda", "--steps"], ["--sector-sensors", "--grid-free-mm", "--sector-maps"]),
    ("sector", ["--sector-sensors", "--sector-maps", "--dyna-planning"], ["--targets", "--grid-free-mm"]),
    ("sector-memory", ["--grid-free-mm", "--sector-maps", "--sector-lr-end"], ["--targets", "--sector-sensors",
                                                                               "--learner-lambda"]),
])
def test_train_help_after_an_encoding_shows_what_that_encoding_reads(encoding, shown, hidden):
    """`qnav train --encoding E --help` is the options training E reads (a cell user reads under
    60 lines); `qnav train --help` still lists every encoding's, in one group per encoding."""
    import contextlib
    import io

    from ground_station import cli

    def help_text(*argv: str) -> str:
        out = io.StringIO()
        with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as done:
            cli.main(["train", *argv, "--help"])
        assert done.value.code == 0
        return out.getvalue()

    text = help_text("--encoding", encoding)
    flags = set(re.findall(r"(--[a-z][a-z-]+)", text))
    assert set(shown) <= flags and not set(hidden) & flags, (encoding, sorted(flags))
    if encoding == "cell":
        assert len(text.splitlines()) < 60
    full = help_text()
    assert set(shown + hidden) <= set(re.findall(r"(--[a-z][a-z-]+)", full))
    assert "sector-memory encoding:" in full and "cell encoding:" in full


@pytest.mark.parametrize(("argv", "words"), [
    (["train", "--steps", "1e6x"], "argument --steps: expected an integer"),
    (["mode", "autp"], "invalid choice: 'autp'"),
    (["arm", "--timeout", "-1"], "argument --timeout: must be > 0"),
    (["bench", "train", "--steps", "2e6x"], "argument --steps"),
    (["no-such-command"], "invalid choice: 'no-such-command'"),
])
def test_usage_errors_are_one_line_with_exit_2(argv, words):
    """A usage error is one line naming what is wrong and where the help is, not the usage block."""
    out = subprocess.run([sys.executable, "-m", "ground_station.cli", *argv], capture_output=True, text=True,
                         timeout=60)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and words in lines[0] and "--help" in lines[0], out.stderr


def test_eval_plot_arrows_point_the_way_the_greedy_action_goes():
    """On the image (row 0 at the top, origin "upper"), a cell whose greedy action is "south"
    (the next row) gets an arrow pointing down (+v): the plot once drew every north/south arrow
    backwards, so a policy with 100 % success looked broken."""
    from firmware_py import robot_spec
    from ground_station.learn.cell.evaluate import greedy_arrows
    from ground_station.maps import load_map

    gm = load_map("paper10")
    h, w = gm.height, gm.width
    q = np.zeros((h * w, len(robot_spec.CELL_ACTION_DELTAS)))
    south = robot_spec.CELL_ACTION_DELTAS.index((0, 1))
    north = robot_spec.CELL_ACTION_DELTAS.index((0, -1))
    q[:, south] = 1.0
    q[0 * w + 0, :] = 0.0
    q[0 * w + 0, north] = 1.0  # cell (0, 0): north
    x, y, u, v = greedy_arrows(q, gm, 0, (w - 1, h - 1))
    at = {(int(c), int(r)): (du, dv) for c, r, du, dv in zip(x, y, u, v, strict=True)}
    assert all(uv == (0.0, 1.0) for cell, uv in at.items() if cell != (0, 0))  # south: down the image
    assert at[(0, 0)] == (0.0, -1.0)  # north: up the image
