"""Tabular learners beside Q-learning (ground_station/learn/cell/learners.py): the
switch's q path equals the Q-learning kernel, every learner is deterministic
per seed and reaches the goal on a small map, Double Q keeps two tables,
Watkins' Q(lambda) cuts its traces on exploratory actions, Dyna-Q plans."""

from dataclasses import replace

import numpy as np
import pytest

from ground_station.learn.cell.evaluate import evaluate_cell
from ground_station.learn.cell.learners import Q_LAMBDA, CellLearner, trace_capacity
from ground_station.learn.cell.trainer import CellProblem, train_cell
from ground_station.learn.config import LEARNERS, TrainConfig, validate_config
from ground_station.maps import GridMap, load_map, parse_map

SMALL = TrainConfig.of(map="paper10", encoding="cell", targets="A,B,C,D", steps=200_000, lr=0.1,
                    chunk_steps=70_001)


def corridor(n: int) -> GridMap:
    occ = parse_map(f"type octile\nheight 1\nwidth {n}\nmap\n{'.' * n}\n").occ
    return GridMap(f"corridor{n}", occ, {"G": (n - 1, 0)})


def test_learner_q_through_the_switch_equals_the_q_learning_kernel():
    gm = load_map("paper10")
    ref = train_cell(SMALL, gm)
    prob = CellProblem.build(gm, SMALL.options.targets)
    lrn = CellLearner(SMALL, prob, np.zeros((prob.encoder.n_states, 4)))
    rets = []
    while lrn.done < SMALL.steps:
        rets.append(lrn.run(min(SMALL.chunk_steps, SMALL.steps - lrn.done))[0])
    assert np.array_equal(lrn.table(), ref.q)
    assert np.array_equal(np.concatenate(rets), ref.returns)


@pytest.mark.parametrize("learner", [x for x in LEARNERS if x != "q"])
def test_each_learner_is_deterministic_and_reaches_the_goals(learner):
    gm = load_map("paper10")
    cfg = replace(SMALL, learner=learner)
    a = train_cell(cfg, gm)
    b = train_cell(replace(cfg, chunk_steps=200_000), gm)  # chunking does not matter
    assert np.array_equal(a.q, b.q) and np.array_equal(a.returns, b.returns)
    other = train_cell(replace(cfg, seed=1), gm)
    # another seed: other episodes (the table may reach the same fixed point: Dyna-Q finds Q* exactly)
    assert not np.array_equal(a.returns, other.returns)
    ref = train_cell(SMALL, gm)  # a different algorithm, not q under another name
    assert not np.array_equal(a.returns, ref.returns) or not np.array_equal(a.q, ref.q)
    ev = evaluate_cell(a.q, gm, [tuple(g) for g in a.meta["goals"]])
    assert ev["success_rate"] >= 0.9, ev  # SARSA needs a small lr (docs/training.md, learner study)


def test_double_q_keeps_two_tables_and_acts_on_their_mean():
    gm = load_map("paper10")
    res = train_cell(replace(SMALL, learner="double-q"), gm)
    assert res.q2 is not None and res.q2.shape == res.q.shape
    qa = 2 * res.q - res.q2
    assert not np.allclose(qa, res.q2)  # the coin updated each table on different steps
    assert np.count_nonzero(qa) > 0 and np.count_nonzero(res.q2) > 0
    assert train_cell(SMALL, gm).q2 is None


def test_watkins_q_lambda_cuts_traces_on_exploratory_actions():
    # open 12x3 room; RIGHT is greedy everywhere and a tiny lr keeps it so; half the
    # actions explore. After every step that continues the episode: a greedy next
    # action extends the trace ring by one, an exploratory one empties it.
    occ = parse_map("type octile\nheight 3\nwidth 12\nmap\n" + "............\n" * 3).occ
    gm = GridMap("room12x3", occ, {"G": (11, 1)})
    cfg = TrainConfig.of(map="room12x3", encoding="cell", steps=1, lr=1e-9, learner="q-lambda",
                      learner_lambda=0.9, trace_min=1e-9, epsilon_start=0.5, epsilon_end=0.5, seed=3,
                      max_episode_steps=1000)
    prob = CellProblem.build(gm, None)
    q = np.full((prob.encoder.n_states, 4), -0.5)
    q[:, 3] = 0.0
    lrn = CellLearner(cfg, prob, q)
    assert lrn.code == Q_LAMBDA and lrn.mem.tr_s.shape[0] > 50
    cuts = grows = 0
    for _ in range(400):
        before = int(lrn.mem.tr[1]) if lrn.ep[3] == 1 else 0  # a new episode empties the ring
        lrn.run(1)
        if lrn.ep[3] == 0:
            continue  # episode over: the next one starts with empty traces
        if int(lrn.ep[4]) == 3:
            assert lrn.mem.tr[1] == before + 1
            grows += 1
        else:
            assert lrn.mem.tr[1] == 0
            cuts += 1
    assert cuts > 20 and grows > 20


def test_trace_capacity_follows_trace_min():
    cfg = TrainConfig.of(gamma=0.95, learner_lambda=0.9, trace_min=1e-3)
    k = trace_capacity(cfg, 10_000)
    assert (0.95 * 0.9) ** (k - 1) < 1e-3 <= (0.95 * 0.9) ** (k - 2)
    assert trace_capacity(replace(cfg, learner_lambda=1.0, gamma=1.0), 77) == 77


def test_dyna_q_plans_from_its_model():
    gm = load_map("paper10")
    cfg = replace(SMALL, learner="dyna-q", steps=3_000, dyna_planning=20)
    prob = CellProblem.build(gm, SMALL.options.targets)
    lrn = CellLearner(cfg, prob, np.zeros((prob.encoder.n_states, 4)))
    lrn.run(3_000)
    seen = lrn.mem.seen[: lrn.mem.n_seen[0]]
    assert len(seen) == len(set(seen.tolist())) > 0
    assert np.all(lrn.mem.model_s2[seen] >= 0)
    # with planning, far more of the table has moved than real steps alone reach in 3k steps
    q_only = CellLearner(replace(cfg, learner="q"), prob, np.zeros((prob.encoder.n_states, 4)))
    q_only.run(3_000)
    ev_d = evaluate_cell(lrn.table(), gm, prob.goals)["success_rate"]
    ev_q = evaluate_cell(q_only.table(), gm, prob.goals)["success_rate"]
    assert ev_d > ev_q


def test_sector_memory_refuses_other_learners():
    with pytest.raises(ValueError, match="sector-memory training: q"):
        validate_config(TrainConfig.of(encoding="sector-memory", learner="sarsa"))
    validate_config(TrainConfig.of(encoding="sector", learner="sarsa"))  # tests/ground_station/test_sector_learners.py
    with pytest.raises(ValueError, match="learner must be one of"):
        validate_config(TrainConfig.of(learner="td0"))
