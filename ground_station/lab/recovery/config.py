"""The recovery learner's one config dataclass (`RecoveryConfig`)."""

from __future__ import annotations

from dataclasses import dataclass

# generated training maps: never the held-out maps of docs/results.md's study (seeds 3xx, 4xx)
TRAIN_MAPS = ("rooms-16x16-s101", "maze-16x16-s102", "maze-20x20-s103", "trap-16x16-s104",
              "random-12x12-s105", "rooms-20x20-s106", "maze-12x12-s107", "paper10")


@dataclass(frozen=True)
class RecoveryConfig:
    """Training of the recovery table: episodes in the twin with the shipped sector table steering,
    a mix of benches per round (6 discs + 3 non-yielding movers, 3 + 2 yielding, blocked passages
    with 2 movers), epsilon-greedy at the decision events, Q-learning sweeps over every transition
    so far (semi-Markov: a transition's reward is the time it took, the last one's adds the
    episode's outcome)."""

    maps: tuple[str, ...] = TRAIN_MAPS
    seed: int = 0
    rounds: int = 6  # rounds of (collect episodes, update)
    episodes: int = 20  # per map and bench (round 0 draws them; 3 benches)
    workers: int = 2
    epsilon_start: float = 0.3
    epsilon_end: float = 0.05
    alpha: float = 0.1
    sweeps: int = 20  # Q-learning passes over the replay of all transitions after each round
    cost_per_s: float = 0.01  # reward per second of robot time
    reward_success: float = 1.0  # goal reached; or "no route" said where none exists
    reward_wrong_no_route: float = -1.0  # "no route" where one exists
    reward_fail: float = -1.0  # timeout or loop (on a blocked episode without a detour: no answer)
    reward_collision: float = -2.0
    init_margin: float = 0.05  # Q starts at the rule table (rule.rule_table) times this
