"""The learner's episodes: the twin (`lab.nav.planned.rollout`, the robot's own planner code) with a
`PlannedTarget` whose recovery decisions come from a float Q table, epsilon-greedy, logged per event.

`collect(job)` runs one job (a worker's share: episodes, or a map's to draw with `draw`; maps, the
table, epsilon, a seed) and returns per episode the episode, its decisions (period, state,
action), periods, outcome and blocked label."""

from __future__ import annotations

import random
from array import array
from typing import Any

import numpy as np

from firmware_py import robot_spec
from firmware_py.kinds.sector import decide
from firmware_py.kinds.sector.recoveries import PlannedTarget


class ExploringTarget(PlannedTarget):
    """`PlannedTarget` choosing its recovery actions epsilon-greedily on a float table (`q`), each
    decision logged as (period, state, action)."""

    q: np.ndarray
    epsilon: float
    rng: random.Random
    log: list[tuple[int, int, int]]
    now_us: int = 0

    def target(self, now_us: int, *args: Any) -> tuple[float, float, int]:
        self.now_us = now_us
        return super().target(now_us, *args)

    def _choose(self, state: int) -> int:
        valid = decide.VALID[decide.event_of(state)]
        if self.rng.random() < self.epsilon:
            a = self.rng.choice(valid)
        else:
            row = self.q[state]
            a = max(valid, key=lambda v: (row[v], -v))
        self.log.append((self.now_us // robot_spec.CONTROL_PERIOD_US, state, a))
        return a


def draw(map: str, n: int, seed: int) -> list:
    """A training map's episodes: `n` each of 6 discs + 3 non-yielding movers and 3 + 2 yielding,
    and up to `n` blocked-passage episodes with 2 movers, half with a detour and half without (a
    map without a label's passage has none of it)."""
    import contextlib

    from ground_station.lab.nav.scenario import (
        MOVER_SPEED_MM_S,
        MoverStyle,
        blocked_episodes,
        episodes,
    )
    from ground_station.maps import MapError, load_map

    gm = load_map(map)
    yields = MoverStyle(speed=MOVER_SPEED_MM_S)
    eps = episodes(gm, n, seed, 6, 3, movers=MoverStyle(speed=MOVER_SPEED_MM_S, yields=False))
    eps += episodes(gm, n, seed, 3, 2, movers=yields)
    for label in (True, False):  # "no route" is right on one label, wrong on the other
        with contextlib.suppress(MapError):
            eps += blocked_episodes(gm, (n + 1) // 2, seed, label, 0, 2, movers=yields)
    return eps


def collect(job: dict) -> list[dict]:
    """One worker's episodes (module docstring)."""
    from firmware_py.policy import load_policy
    from firmware_py.shipped_policies import resolve_policy_spec
    from ground_station.lab.nav import planned
    from ground_station.lab.nav.controllers import standard_controllers
    from ground_station.lab.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, OUTCOMES, STALL_STEPS
    from ground_station.maps import load_map

    ctrl = standard_controllers(load_policy(str(resolve_policy_spec(job["policy"]))), ("learnt",))[0]
    maps = {name: load_map(spec) for name, spec in job["maps"].items()}
    q = np.asarray(job["q"], dtype=np.float64)
    rng = random.Random(job["seed"])
    out = []
    made: list[ExploringTarget] = []

    def make(grid: Any, cfg: Any, work: Any, radius_mm: int) -> PlannedTarget:
        t = ExploringTarget(grid, cfg, work, radius_mm, decide.RecoveryTable(array("b")))
        t.q, t.epsilon, t.rng, t.log = q, job["epsilon"], rng, []
        made.append(t)
        return t

    for ep in job.get("episodes") or draw(**job["draw"]):
        made.clear()
        o, _, steps, _, _, _ = planned.rollout(ep, maps[ep.map], ctrl, BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS,
                                               make_planner=make)
        out.append({"episode": ep, "decisions": made[0].log, "periods": int(steps), "outcome": OUTCOMES[o],
                    "detour": None if not ep.blocked else bool(ep.blocked["detour"])})
    return out
