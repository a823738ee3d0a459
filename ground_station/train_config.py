"""Training configuration: every hyperparameter in one dataclass.

Kept apart from `ground_station.train` (which re-exports it) so that building
the `qnav` argument parser does not import numba: the field help texts
become `qnav train --help`.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field, fields


def _f(default, help: str):
    return field(default=default, metadata={"help": help})


@dataclass
class TrainConfig:
    """All training hyperparameters; `asdict(cfg)` is stored in meta.json."""

    map: str = _f("paper10", "built-in map name, generator spec (e.g. trap-16x16-s0) or path to a .map file")
    encoding: str = _f("cell", "state encoding: cell (robot cell x goal) or sector (kinematic twin)")
    targets: str = _f("", "comma-separated target names or col:row cells (cell encoding); empty = all map targets")
    seed: int = _f(0, "random seed; same seed and config -> bit-identical table")
    steps: int = _f(3_000_000, "environment steps (Q updates) to train for")
    lr: float = _f(0.5, "learning rate eta in the Q update")
    gamma: float = _f(0.95, "discount factor gamma")
    epsilon_start: float = _f(1.0, "exploration rate at step 0 (epsilon-greedy)")
    epsilon_end: float = _f(0.1, "exploration rate after the decay")
    epsilon_decay: float = _f(0.5, "fraction of `steps` over which epsilon falls linearly from start to end")
    max_episode_steps: int = _f(0, "episode step limit (truncation, bootstrapped); 0 = width*height of the map")
    reward_goal: float = _f(1.0, "reward for reaching the goal (episode ends)")
    reward_step: float = _f(-0.01, "reward for every other move")
    reward_collision: float = _f(-1.0, "reward for hitting an obstacle or the map edge (episode ends)")
    q_init_scale: float = _f(0.0, "initial Q values uniform in [-scale, scale] (the paper initialises randomly); 0 = zeros")
    curve_points: int = _f(200, "number of episode windows in the learning curve")
    chunk_steps: int = _f(1_000_000, "steps per kernel call (progress bar granularity)")


def add_config_arguments(parser: argparse.ArgumentParser, skip: tuple[str, ...] = ()) -> None:
    """One `--flag` per TrainConfig field, with the field's help text."""
    for f in fields(TrainConfig):
        if f.name in skip:
            continue
        flag = "--" + f.name.replace("_", "-")
        parser.add_argument(flag, type=type(f.default), default=f.default, dest=f.name,
                            help=f"{f.metadata.get('help', '')} (default: {f.default})")


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    return TrainConfig(**{f.name: getattr(args, f.name) for f in fields(TrainConfig) if hasattr(args, f.name)})


def validate_config(cfg: TrainConfig) -> None:
    """Raise ValueError (one line) on an impossible configuration."""
    if cfg.encoding not in ("cell", "sector"):
        raise ValueError(f"encoding must be cell or sector, got {cfg.encoding!r}")
    if cfg.steps < 1:
        raise ValueError(f"steps must be >= 1, got {cfg.steps}")
    if not 0.0 < cfg.lr <= 1.0:
        raise ValueError(f"lr must be in (0, 1], got {cfg.lr}")
    if not 0.0 <= cfg.gamma <= 1.0:
        raise ValueError(f"gamma must be in [0, 1], got {cfg.gamma}")
    for name in ("epsilon_start", "epsilon_end", "epsilon_decay"):
        v = getattr(cfg, name)
        if not 0.0 <= v <= 1.0:
            raise ValueError(f"{name} must be in [0, 1], got {v}")
    if cfg.max_episode_steps < 0 or cfg.curve_points < 1 or cfg.chunk_steps < 1:
        raise ValueError("max_episode_steps must be >= 0, curve_points and chunk_steps >= 1")
