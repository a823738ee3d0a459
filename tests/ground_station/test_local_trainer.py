"""The follower's Q-learning on the local planner's sub-goals (learn/sector/local_trainer.py):
seeded, trained on the training maps only, and a contact ends the episode with -collision."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ground_station.learn.sector.local_trainer import (
    BENCH_MAPS,
    TRAIN_MAPS,
    LocalFollowerConfig,
    LocalFollowerTrainer,
)
from ground_station.learn.sector.twin import RADIUS_MM

SMALL = {"periods": 1500, "pool": 12}


def _start_table() -> np.ndarray:
    rng = np.random.default_rng(3)
    return rng.uniform(-0.1, 0.1, size=(405, 4))


def test_short_run_changes_the_table_deterministically() -> None:
    q0 = _start_table()
    tables = []
    for _ in range(2):
        q = q0.copy()
        stats = LocalFollowerTrainer(LocalFollowerConfig(seed=5, **SMALL)).run(q, progress=False)
        assert stats.periods == SMALL["periods"]
        assert stats.episodes >= 1
        tables.append(q)
    assert not np.array_equal(tables[0], q0)
    np.testing.assert_array_equal(tables[0], tables[1])
    q = q0.copy()
    LocalFollowerTrainer(LocalFollowerConfig(seed=6, **SMALL)).run(q, progress=False)
    assert not np.array_equal(q, tables[0])


def test_pool_comes_from_training_maps_only() -> None:
    tr = LocalFollowerTrainer(LocalFollowerConfig(seed=1, pool=40, periods=1))
    used = {ep.map for ep in tr.pool}
    assert used <= set(TRAIN_MAPS)
    assert not used & (set(BENCH_MAPS) - set(TRAIN_MAPS))
    assert len(used) >= 3  # draws over the maps, not one
    assert any(not ep.discs and not ep.movers for ep in tr.pool)  # plain waypoint following stays in the mix
    mixed = LocalFollowerTrainer(LocalFollowerConfig(seed=1, pool=10, periods=1, clear_share=0.5))
    assert len(mixed.clear_pool) == 10
    assert all(not ep.discs and not ep.movers and ep.map in TRAIN_MAPS for ep in mixed.clear_pool)
    with pytest.raises(ValueError, match="bench maps"):
        LocalFollowerTrainer(LocalFollowerConfig(maps=("paper10", "maze-16x16-s1"), pool=2, periods=1))


def test_collision_gives_minus_collision_and_ends_the_episode() -> None:
    cfg = LocalFollowerConfig(seed=2, pool=4, periods=1000, lr=0.1, lr_end=0.1, eps_start=0.0, eps_end=0.0,
                              noise_mm=0.0, collision=1.0)
    tr = LocalFollowerTrainer(cfg)
    ep = tr.pool[0]
    x, y, th = ep.start
    d = RADIUS_MM + 60.0 + 5.0  # a disc 5 mm ahead of the rim: the first forward period touches it
    ep = dataclasses.replace(ep, discs=[(x + d * math.cos(th), y + d * math.sin(th), 60.0)], movers=[])
    q = np.zeros((405, 4))
    q[:, 0] = 0.5  # greedy = forward everywhere
    outcome, ret, periods = tr.episode(q, ep, 1000)
    assert (outcome, periods) == ("collision", 1)
    assert ret == -1.0
    changed = np.argwhere(q != np.where(np.arange(4) == 0, 0.5, 0.0))
    assert changed.shape == (1, 2) and changed[0, 1] == 0  # one update, of forward, terminal (no bootstrap)
    s0 = changed[0, 0]
    assert q[s0, 0] == pytest.approx(0.5 + 0.1 * (-1.0 - 0.5))
