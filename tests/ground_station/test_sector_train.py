"""SectorTrainer and evaluate_sector: determinism, chunking, API shape, every
hyperparameter taken from the TrainConfig."""

import numpy as np
import pytest

from firmware_py.kinds.sector.encoder import SectorEncoder
from ground_station.learn.envs.sector_env import SectorNavEnv
from ground_station.learn.sector.evaluate import eval_episodes, evaluate_sector
from ground_station.learn.sector.reward import SectorReward
from ground_station.learn.sector.trainer import SectorTrainer, epsilon_schedule
from ground_station.learn.train import TrainConfig
from ground_station.maps import GridMap, load_map


def _cfg(**kw):
    base = dict(encoding="sector", seed=3, steps=60_000, lr=0.1, gamma=0.95, max_episode_steps=400)
    base.update(kw)
    return TrainConfig.of(**base)


def _train(cfg, chunks, maps=None):
    enc = SectorEncoder()
    tr = SectorTrainer(maps or [load_map("paper10")], cfg, enc)
    q = np.zeros((tr.n_states, tr.n_actions))
    rets, succ = [], []
    done = 0
    for n in chunks:
        r, s = tr.run(q, done, n)
        rets.append(r)
        succ.append(s)
        done += n
    return q, np.concatenate(rets), np.concatenate(succ)


def test_same_seed_same_table_and_chunking_does_not_matter():
    cfg = _cfg()
    q1, r1, s1 = _train(cfg, [60_000])
    q2, r2, s2 = _train(cfg, [10_000, 25_000, 25_000])
    assert np.array_equal(q1, q2) and np.array_equal(r1, r2) and np.array_equal(s1, s2)
    assert len(r1) > 10 and np.any(q1 != 0)
    q3, _, _ = _train(_cfg(seed=4), [60_000])
    assert not np.array_equal(q1, q3)


def test_every_sector_hyperparameter_comes_from_the_config():
    cfg = _cfg(sector_hold_max=7, sector_progress_reward=0.5, sector_reverse_cost=0.3, reward_step=-0.02,
               reward_goal=0.8, reward_collision=-0.9, sector_align_reward=0.0, sector_lr_end=0.05,
               sector_range_noise_mm=0.0, epsilon_end=0.2, epsilon_decay=0.25)
    tr = SectorTrainer([load_map("paper10")], cfg, SectorEncoder())
    assert (tr.hold_max, tr.lr_end, tr.noise_mm) == (7, 0.05, 0.0)
    assert tr.reward == SectorReward(progress=0.5, step_cost=0.02, reverse_cost=0.3, goal=0.8, collision=0.9,
                                     align=0.0)
    assert epsilon_schedule(cfg) == (1.0, 0.2, 15_000)
    # the hold limit reaches the kernel: one-step updates learn a different table
    q_hold, _, _ = _train(_cfg(), [20_000])
    q_one, _, _ = _train(_cfg(sector_hold_max=1), [20_000])
    assert not np.array_equal(q_hold, q_one)


def test_env_and_trainer_share_the_default_reward():
    assert SectorNavEnv().reward == SectorTrainer([load_map("paper10")], TrainConfig.of(encoding="sector"),
                                                  SectorEncoder()).reward == SectorReward.from_config(TrainConfig.of(encoding="sector"))


def test_trainer_shape_and_bad_table():
    enc = SectorEncoder()
    tr = SectorTrainer([load_map("paper10"), load_map("trap-12x12-s1")], _cfg(), enc)
    assert (tr.n_states, tr.n_actions) == (enc.n_states, enc.n_actions)
    with pytest.raises(ValueError, match="float64"):
        tr.run(np.zeros((3, 4)), 0, 10)
    r, s = tr.run(np.zeros((tr.n_states, tr.n_actions)), 0, 20_000)
    assert r.shape == s.shape and s.dtype == bool


def test_learning_beats_an_untrained_table_on_an_open_map():
    # an open 6x6 room: goal seeking is learnable quickly, a zero table (always
    # forward) reaches only the goals straight ahead
    gm = GridMap("open6", np.zeros((6, 6), dtype=bool))
    enc = SectorEncoder()
    q, _, _ = _train(_cfg(steps=1_500_000, lr=0.1, gamma=0.9), [1_500_000], maps=[gm])
    trained = evaluate_sector(q, gm, enc, sample=800, seed=1)
    zero = evaluate_sector(np.zeros_like(q), gm, enc, sample=800, seed=1)
    assert trained["success_rate"] > zero["success_rate"] + 0.3


def test_evaluation_is_deterministic_and_complete():
    gm = load_map("paper10")
    enc = SectorEncoder()
    rng = np.random.default_rng(0)
    q = rng.normal(size=(enc.n_states, enc.n_actions))
    a = evaluate_sector(q, gm, enc, seed=7, sample=500)
    b = evaluate_sector(q, gm, enc, seed=7, sample=500)
    assert a == b
    assert a["episodes"] == 500
    assert a["timeouts"] + a["collisions"] + a["loops"] + round(a["success_rate"] * 500) == 500
    starts, goals, heads = eval_episodes(gm, headings=8)
    n_free = len(gm.free_cells())
    assert len(starts) == n_free * (n_free - 1) * 8  # paper10 is connected
    assert not np.any(np.all(starts == goals, axis=1))
