"""Tabular Q-learning of the recovery decisions (`firmware_py.kinds.sector.decide`), and the
training loop: per round, episodes in the twin on the training maps with the current table
epsilon-greedy (`rollouts.collect`, over a process pool), then `sweeps` passes of the Q-learning
update over every transition collected so far (experience replay: Q-learning is off-policy).
Round 0 draws and runs `episodes` per map per bench (`rollouts.draw`); later rounds run again only
those in which a decision was taken (the others carry no transition: the twin is deterministic
up to the table's choices, so an episode without an event has none whatever the table).

A transition runs from one decision to the next in the same episode (semi-Markov, undiscounted:
episodes are bounded by the bench's budget); its reward is -`cost_per_s` x the robot time between
them, and the last decision's adds the episode's outcome (`terminal_reward`).

`python -m ground_station.lab.recovery.qlearn --out FILE.qtab` trains and writes the shipped
sector policy with the table in its `recovery_table` metadata (`export`)."""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict

import numpy as np

from firmware_py import robot_spec
from firmware_py.kinds.sector import decide
from ground_station.lab.recovery.config import RecoveryConfig
from ground_station.lab.recovery.rule import rule_table

PERIOD_S = robot_spec.CONTROL_PERIOD_US / 1e6
Transition = tuple[int, int, float, int]  # state, action, reward, next state (-1: the episode ended)


def terminal_reward(outcome: str, detour: bool | None, cfg: RecoveryConfig) -> float:
    """The episode's outcome as a reward: `detour` is the blocked label (None: not a blocked episode,
    a route exists)."""
    if outcome == "success":
        return cfg.reward_success
    if outcome == "no_route":
        return cfg.reward_success if detour is False else cfg.reward_wrong_no_route
    if outcome == "collision":
        return cfg.reward_collision
    return cfg.reward_fail


def transitions(ep: dict, cfg: RecoveryConfig) -> list[Transition]:
    """An episode's decisions (period, state, action) as transitions."""
    d = ep["decisions"]
    out = []
    for i, (t, s, a) in enumerate(d):
        if i + 1 < len(d):
            t2, s2, _ = d[i + 1]
            out.append((s, a, -cfg.cost_per_s * (t2 - t) * PERIOD_S, s2))
        else:
            r = -cfg.cost_per_s * (ep["periods"] - t) * PERIOD_S + terminal_reward(ep["outcome"], ep["detour"], cfg)
            out.append((s, a, r, -1))
    return out


def valid_mask() -> np.ndarray:
    m = np.zeros((decide.N_STATES, decide.N_ACTIONS), dtype=bool)
    for s in range(decide.N_STATES):
        m[s, list(decide.VALID[decide.event_of(s)])] = True
    return m


def sweep(q: np.ndarray, trans: list[Transition], alpha: float, valid: np.ndarray) -> None:
    """One pass of the Q-learning update over `trans` (in place): Q(s,a) += alpha (r + max_valid
    Q(s') - Q(s,a))."""
    for s, a, r, s2 in trans:
        target = r if s2 < 0 else r + float(q[s2][valid[s2]].max())
        q[s, a] += alpha * (target - q[s, a])


def train(cfg: RecoveryConfig, policy: str = "policies:sector", log=print,
          checkpoint: str | None = None, stop_after: int | None = None) -> tuple[np.ndarray, dict]:
    """The float table after `cfg.rounds` rounds (or the first `stop_after` of them, on the same
    epsilon schedule), and the training record (per round: episodes, success, decisions, wall time)."""
    from concurrent.futures import ProcessPoolExecutor

    from ground_station.lab.recovery.rollouts import collect
    from ground_station.maps import load_map

    valid = valid_mask()
    q = np.where(valid, rule_table() * cfg.init_margin, -1.0)
    maps = {load_map(m).name: m for m in cfg.maps}
    replay: list[Transition] = []
    record = []
    pool_eps: list = []  # the episodes with a decision event (round 0 finds them)
    with ProcessPoolExecutor(cfg.workers) as pool:
        for rnd in range(min(cfg.rounds, stop_after or cfg.rounds)):
            t0 = time.perf_counter()
            frac = rnd / max(1, cfg.rounds - 1)
            epsilon = cfg.epsilon_start + (cfg.epsilon_end - cfg.epsilon_start) * frac
            base = {"policy": policy, "maps": maps, "q": q.tolist(), "epsilon": epsilon}
            if rnd == 0:  # the episodes, drawn in the workers (one job a map), all run once
                jobs = [{**base, "seed": cfg.seed * 100 + i, "draw": {"map": spec, "n": cfg.episodes,
                                                                      "seed": cfg.seed}}
                        for i, spec in enumerate(maps.values())]
            else:  # then only those where a decision was taken: the others carry no transition
                n = cfg.workers * 4
                jobs = [{**base, "seed": (cfg.seed * 1000 + rnd) * 100 + i, "episodes": pool_eps[i::n]}
                        for i in range(n) if pool_eps[i::n]]
            rows = [r for part in pool.map(collect, jobs) for r in part]
            if rnd == 0:
                pool_eps = [r["episode"] for r in rows if r["decisions"]]
            for r in rows:
                replay += transitions(r, cfg)
            for _ in range(cfg.sweeps):
                sweep(q, replay, cfg.alpha, valid)
            rec = {"round": rnd, "episodes": len(rows), "epsilon": round(epsilon, 3),
                   "success": round(sum(r["outcome"] == "success" for r in rows) / len(rows), 4),
                   "decisions": sum(len(r["decisions"]) for r in rows), "replay": len(replay),
                   "wall_s": round(time.perf_counter() - t0, 1)}
            record.append(rec)
            log(json.dumps(rec))
            if checkpoint:
                np.save(checkpoint, q)
    return q, {"config": asdict(cfg), "stop_after": stop_after, "rounds": record}


def int8_table(q: np.ndarray) -> decide.RecoveryTable:
    """The float table as the robot's int8 one (symmetric, one scale; invalid actions -127), rows
    whose valid maximum is unique in float untied after rounding (`learn.export.untie_argmax`: the
    robot breaks ties to the lowest index, which is not the learnt choice)."""
    from array import array

    from ground_station.learn.export import untie_argmax

    valid = valid_mask()
    scale = float(np.abs(q[valid]).max()) / 127 or 1.0
    t = np.where(valid, np.clip(np.round(q / scale), -127, 127), -127).astype(np.int8)
    t, _ = untie_argmax(np.where(valid, q, -np.inf), t, 127)
    return decide.RecoveryTable(array("b", t.tobytes()), scale)


def export(q: np.ndarray, out: str, record: dict, policy: str = "policies:sector") -> None:
    """The sector policy `policy` with the table in its metadata (`decide.META_KEY`), written to `out`."""
    from pathlib import Path

    from ground_station.lab.nav.controllers import with_recovery_table

    Path(out).write_bytes(with_recovery_table(policy, int8_table(q), record))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="the .qtab to write (the sector policy with its recovery table)")
    p.add_argument("--policy", default="policies:sector", help="the sector policy it steers with")
    p.add_argument("--rounds", type=int, default=RecoveryConfig.rounds)
    p.add_argument("--episodes", type=int, default=RecoveryConfig.episodes, help="per map per round")
    p.add_argument("--workers", type=int, default=RecoveryConfig.workers)
    p.add_argument("--seed", type=int, default=RecoveryConfig.seed)
    p.add_argument("--stop-after", type=int, default=None, metavar="R",
                   help="stop after R rounds (the epsilon schedule stays the one of --rounds)")
    a = p.parse_args(argv)
    cfg = RecoveryConfig(rounds=a.rounds, episodes=a.episodes, workers=a.workers, seed=a.seed)
    q, record = train(cfg, a.policy, checkpoint=a.out + ".npy", stop_after=a.stop_after)
    export(q, a.out, record, a.policy)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
