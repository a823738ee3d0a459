"""Tabular learners on the sector encoding (the switch in
`ground_station.learn.sector.kernels.train_kernel`): each is deterministic
per seed and independent of chunking, is not Q-learning under another name,
learns on a small room; Double Q keeps two tables and ships their mean,
Dyna-Q's model holds what was seen, Q(lambda)'s traces are bounded and cut;
sector-memory refuses them."""

from dataclasses import replace

import numpy as np
import pytest

from firmware_py.kinds.sector.encoder import SectorEncoder
from ground_station.lab.sweep import with_values
from ground_station.learn.config import LEARNERS, TrainConfig, validate_config
from ground_station.learn.sector.evaluate import evaluate_sector
from ground_station.learn.sector.kernels import L_Q_LAMBDA
from ground_station.learn.sector.trainer import SectorTrainer, sector_encoder, train_sector
from ground_station.maps import GridMap, load_map

CFG = TrainConfig.of(encoding="sector", map="paper10", seed=3, steps=60_000, lr=0.1, gamma=0.95,
                  max_episode_steps=400, dyna_planning=5)
OPEN6 = GridMap("open6", np.zeros((6, 6), dtype=bool))


def _train(cfg, chunks, maps=None, encoder=None):
    tr = SectorTrainer(maps or [load_map("paper10")], cfg, encoder or SectorEncoder())
    q = np.zeros((tr.n_states, tr.n_actions))
    rets, done = [], 0
    for n in chunks:
        rets.append(tr.run(q, done, n)[0])
        done += n
    return tr, q, np.concatenate(rets)


@pytest.mark.parametrize("learner", [x for x in LEARNERS if x != "q"])
def test_each_learner_is_deterministic_chunk_free_and_not_q(learner):
    cfg = replace(CFG, learner=learner)
    validate_config(cfg)
    _, q1, r1 = _train(cfg, [60_000])
    _, q2, r2 = _train(cfg, [7_000, 23_000, 30_000])
    assert np.array_equal(q1, q2) and np.array_equal(r1, r2) and np.any(q1 != 0)
    _, q3, _ = _train(replace(cfg, seed=4), [60_000])
    assert not np.array_equal(q1, q3)
    _, q_ref, r_ref = _train(CFG, [60_000])
    assert not np.array_equal(q1, q_ref)


@pytest.mark.parametrize("learner", LEARNERS)
def test_each_learner_learns_goal_seeking_in_an_open_room(learner):
    cfg = replace(CFG, learner=learner, steps=1_000_000, gamma=0.9)
    tr, q, _ = _train(cfg, [1_000_000], maps=[OPEN6])
    table = tr.table(q)
    trained = evaluate_sector(table, OPEN6, SectorEncoder(), sample=600, seed=1)
    zero = evaluate_sector(np.zeros_like(q), OPEN6, SectorEncoder(), sample=600, seed=1)
    assert trained["success_rate"] > zero["success_rate"] + 0.3, (learner, trained["success_rate"])


def test_double_q_trains_two_tables_and_ships_their_mean():
    cfg = replace(CFG, learner="double-q")
    tr, q, _ = _train(cfg, [60_000])
    assert tr.q2 is not None and not np.allclose(q, tr.q2)
    assert np.count_nonzero(q) > 0 and np.count_nonzero(tr.q2) > 0
    assert np.array_equal(tr.table(q), (q + tr.q2) / 2)
    res = train_sector(replace(cfg, chunk_steps=25_000), load_map("paper10"))
    tr2, qa, _ = _train(cfg, [60_000], encoder=sector_encoder(cfg))
    assert np.array_equal(res.q, tr2.table(qa)) and np.array_equal(res.q2, tr2.q2)  # the run's table is the mean


def test_dyna_q_model_holds_the_pairs_seen_and_planning_moves_more_of_the_table():
    tr, q, _ = _train(replace(CFG, learner="dyna-q", steps=20_000), [20_000])
    seen = tr._mem.seen[: tr._mem.n_seen[0]]
    assert len(seen) == len(set(seen.tolist())) > 10
    m = tr._mem
    assert np.all(m.model_s2[seen] >= 0) and np.all(m.model_g[seen] > 0) and np.all(m.model_g[seen] <= 1)
    unseen = np.setdiff1d(np.arange(tr._mem.model_s2.size), seen)
    assert np.all(tr._mem.model_s2[unseen] == -1)
    _, q_plain, _ = _train(replace(CFG, learner="q", steps=20_000), [20_000])
    assert np.abs(q).sum() > np.abs(q_plain).sum()  # replayed updates spread the values further


def test_q_lambda_traces_are_bounded_and_cut_on_exploration():
    cfg = with_values(CFG, learner="q-lambda", epsilon_start=0.5, epsilon_end=0.5, sector_hold_max=1)
    tr = SectorTrainer([load_map("paper10")], cfg, SectorEncoder())
    assert tr.code == L_Q_LAMBDA and tr._mem.tr_s.shape[0] > 10
    q = np.zeros((tr.n_states, tr.n_actions))
    lengths = [0]
    cap = tr._mem.tr_s.shape[0]
    for i in range(5000):  # hold_max 1: one update per step
        tr.run(q, i, 1)
        n = int(tr._mem.tr[1])
        # a greedy next action extends the chain by one (up to the ring), an exploratory
        # one empties it, a new episode starts from an empty ring
        assert n in (lengths[-1] + 1, 0, 1) or n == lengths[-1] == cap, (lengths[-1], n)
        lengths.append(n)
    assert max(lengths) > 5 and lengths.count(0) > 50


def test_the_sector_encoding_takes_them_and_sector_memory_refuses_them():
    with pytest.raises(ValueError, match="sector-memory training: q"):
        validate_config(TrainConfig.of(encoding="sector-memory", learner="sarsa"))
    validate_config(TrainConfig.of(encoding="sector", learner="expected-sarsa"))
