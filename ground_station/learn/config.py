"""Training configuration: the common hyperparameters in one dataclass, each kind's
own nested in it (`TrainConfig.options`). Kept apart from `ground_station.learn.train`
so that building the `qnav` parser does not import numba: the field help texts become
`qnav train --help`, grouped by the kinds that read them.

Every field has one flat name, its flag without the dashes (`lr`, `targets`,
`sector_guidance`): recipes, `--space` axes, sweep and study jobs and meta.json's
`config` (`TrainConfig.flat()`, `TrainConfig.of(**flat)`) use it.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field, fields
from typing import Any

from ground_station.learn import kinds
from ground_station.learn.cell import LEARNERS  # the tabular learners (learn/cell/learners.py)
from ground_station.learn.sector import int_list

__all__ = ["TrainConfig", "LEARNERS", "encodings", "recipes", "add_config_arguments", "config_from_recipe_args",
           "recipe_config", "validate_config", "int_arg", "int_list", "applies_to"]


_f = kinds.option  # a common field; its help text is its `qnav train --help` line


_LEARNER_FIELDS = {"learner_lambda", "trace_min", "dyna_planning"}


@dataclass
class TrainConfig:
    """All training hyperparameters; `flat()` is stored in meta.json. `options` holds the
    encoding's own (None: its defaults)."""

    map: str = _f("paper10", "built-in map name, generator spec (e.g. trap-16x16-s0) or path to a .map file")
    encoding: str = _f(kinds.DEFAULT, "policy kind to train (ground_station/learn/kinds.py)")
    profile: str = _f("", "robot profile FILE.toml (firmware_py/profile.py, docs/robot-profile.md) the twin plays "
                          "and the policy is trained for: body radius, wheel base, wheel speed limit, sensor angles "
                          "and ranges; empty = the built-in robot")
    learner: str = _f("q", "tabular learner (cell, sector; sector-memory: q): q = Q-learning, sarsa, expected-sarsa, "
                           "double-q, dyna-q, q-lambda = Watkins' Q(lambda) (ground_station/learn/cell/learners.py)")
    learner_lambda: float = _f(0.9, "q-lambda: trace decay lambda (traces decay by gamma * lambda per step)")
    trace_min: float = _f(1e-3, "q-lambda: a trace smaller than this is dropped (bounds the trace ring)")
    dyna_planning: int = _f(10, "dyna-q: simulated updates from the learnt model per real step")
    seed: int = _f(0, "random seed; same seed and config -> bit-identical table")
    steps: int = _f(3_000_000, "environment steps (Q updates) to train for")
    lr: float = _f(0.5, "learning rate eta in the Q update")
    gamma: float = _f(0.95, "discount factor gamma")
    epsilon_start: float = _f(1.0, "exploration rate at step 0 (epsilon-greedy)")
    epsilon_end: float = _f(0.1, "exploration rate after the decay")
    epsilon_decay: float = _f(0.5, "fraction of `steps` over which epsilon falls linearly from start to end")
    max_episode_steps: int = _f(0, "episode step limit (truncation, bootstrapped); 0 = automatic: width*height "
                                   "of the map (cell), 10 x the cells of the largest training map (sector)")
    reward_goal: float = _f(1.0, "reward for reaching the goal (episode ends)")
    reward_step: float = _f(-0.01, "reward for every other move")
    reward_collision: float = _f(-1.0, "reward for hitting an obstacle or the map edge (episode ends)")
    q_init_scale: float = _f(0.0, "initial Q values uniform in [-scale, scale] (the paper initialises randomly); 0 = zeros")
    curve_points: int = _f(200, "number of episode windows in the learning curve")
    chunk_steps: int = _f(1_000_000, "steps per kernel call (progress bar granularity)")

    options: Any = field(default=None, metadata={"help": "the encoding's own hyperparameters"})

    def __post_init__(self) -> None:
        kind = kinds.of_name(self.encoding)
        if self.options is None:
            self.options = kind.options()
        elif not isinstance(self.options, kind.options):
            raise ValueError(f"options of a {self.encoding} config must be {kind.options.__name__}, "
                             f"got {type(self.options).__name__}")

    @classmethod
    def of(cls, **flat: Any) -> TrainConfig:
        """A config from flat names (common fields and the encoding's options); ValueError on a name
        that is neither."""
        encoding = flat.get("encoding", kinds.DEFAULT)
        kind = kinds.of_name(encoding)
        common = {f.name for f in fields(cls)} - {"options"}
        own = {name: f.name for name, f in kind.option_fields()}
        unknown = sorted(set(flat) - common - set(own))
        if unknown:
            raise ValueError(f"{', '.join(unknown)}: not a training option of the {encoding} encoding")
        return cls(**{k: v for k, v in flat.items() if k in common},
                   options=kind.options(**{own[k]: v for k, v in flat.items() if k in own}))

    def flat(self) -> dict[str, Any]:
        """Common fields and the encoding's options by flat name (meta.json's `config`)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "options"}
        out.update({name: getattr(self.options, f.name) for name, f in kinds.of_name(self.encoding).option_fields()})
        return out


def encodings() -> list[str]:
    return kinds.names()


def recipes() -> dict[str, dict[str, Any]]:
    """The shipped recipe of each encoding: flat names that differ from the defaults.
    `qnav train --encoding E` starts from it, command-line flags override it; `--recipe NAME`
    names one (`kinds.shipped_recipes()`, docs/training.md)."""
    return {name: dict(kinds.of_name(name).recipe) for name in kinds.names()}


def recipe_config(encoding: str, given: dict[str, Any]) -> TrainConfig:
    """TrainConfig from the encoding's recipe, then `given` (flat names; explicit values win)."""
    return TrainConfig.of(**{**kinds.of_name(encoding).recipe, **given, "encoding": encoding})


def applies_to(name: str) -> tuple[str, ...]:
    """The encodings whose training reads the field of flat name `name` (its --help section)."""
    every = tuple(kinds.names())
    if name in _LEARNER_FIELDS:
        return tuple(k for k in every if len(kinds.of_name(k).learners) > 1)
    return tuple(kinds.flat_names().get(name, every))


def _group_title(where: tuple[str, ...]) -> str:
    if where == tuple(kinds.names()):
        return "training (every encoding)"
    if all(len(kinds.of_name(k).learners) > 1 for k in where) and len(where) > 1:
        return f"learners other than q ({' and '.join(where)} encodings)"
    return f"{' and '.join(where)} encoding{'s' if len(where) > 1 else ''}"


def _flag_fields() -> list[tuple[str, Any]]:
    """(flat name, field) of every flag: the common fields, then each kind's options once."""
    out = [(f.name, f) for f in fields(TrainConfig) if f.name != "options"]
    seen = {name for name, _ in out}
    for k in kinds.names():
        for name, f in kinds.of_name(k).option_fields():
            if name not in seen:
                seen.add(name)
                out.append((name, f))
    return out


def add_config_arguments(parser: argparse.ArgumentParser, skip: tuple[str, ...] = ()) -> None:
    """One `--flag` per flat name, with the field's help text, grouped by the encodings that read it
    (`applies_to`)."""
    groups: dict[tuple[str, ...], argparse._ArgumentGroup] = {}
    for name, f in _flag_fields():
        if name in skip:
            continue
        where = applies_to(name)
        if where not in groups:
            groups[where] = parser.add_argument_group(_group_title(where))
        kind = type(f.default)
        text = f.metadata.get("help", "")
        if name == "encoding":  # the registered kinds, each with its one-line summary
            text += ": " + "; ".join(f"{k} = {kinds.of_name(k).summary}" for k in kinds.names())
        groups[where].add_argument("--" + name.replace("_", "-"), type=int_arg if kind is int else kind,
                                   default=f.default, dest=name, help=f"{text} (default: {f.default})")


def int_arg(text: str) -> int:
    """An integer option that also takes 1e6, 3_000_000 or 2.5e5 (whole numbers only)."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text.replace("_", ""))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer (1000000, 1e6), got {text!r}") from None
    if not value.is_integer():
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}")
    return int(value)


def validate_config(cfg: TrainConfig) -> None:
    """Raise ValueError (one line) on an impossible configuration."""
    kind = kinds.of_name(cfg.encoding)
    if cfg.learner not in LEARNERS:
        raise ValueError(f"learner must be one of {', '.join(LEARNERS)}, got {cfg.learner!r}")
    if cfg.learner not in kind.learners:
        raise ValueError(f"learner {cfg.learner} is not implemented for the {cfg.encoding} encoding "
                         f"({cfg.encoding} training: {', '.join(kind.learners)})")
    if not 0.0 <= cfg.learner_lambda <= 1.0 or not 0.0 < cfg.trace_min < 1.0 or cfg.dyna_planning < 0:
        raise ValueError("learner_lambda must be in [0, 1], trace_min in (0, 1), dyna_planning >= 0")
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
    from ground_station.learn.robot import training_profile

    training_profile(cfg)  # a bad profile: one line naming the file and the key
    if kind.validate is not None:
        kind.validate(cfg)


def recipe_defaults(parser: argparse.ArgumentParser) -> None:
    """Leave the recipe fields (and --encoding) unset, so `config_from_recipe_args` can tell a
    flag left out (it takes the encoding's recipe) from one given."""
    parser.set_defaults(encoding=None, **{k: None for r in recipes().values() for k in r})


def config_from_recipe_args(args: argparse.Namespace, encoding: str | None = None) -> TrainConfig:
    """TrainConfig from parsed flags, recipe-aware (`qnav train`, `sweep`, `study`): the encoding
    (`encoding`, else --encoding, else cell) picks its recipe; a flag given and read by that
    encoding wins over it, a flag left out takes it."""
    encoding = encoding or getattr(args, "encoding", None) or kinds.DEFAULT
    reads = {name for name, _ in _flag_fields() if encoding in applies_to(name)}
    given = {name: getattr(args, name) for name in reads
             if getattr(args, name, None) is not None and name != "encoding"}
    return recipe_config(encoding, given)
