"""Training configuration: every hyperparameter in one dataclass.

Kept apart from `ground_station.learn.train` (which re-exports it) so that building
the `qnav` argument parser does not import numba: the field help texts
become `qnav train --help`.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field, fields
from typing import Any

ENCODINGS = ("cell", "sector", "sector-memory")
# tabular learners (ground_station/learn/cell/learners.py, the sector trainer's switch in
# ground_station/learn/sector/kernels.py); sector-memory: q only
LEARNERS = ("q", "sarsa", "expected-sarsa", "double-q", "dyna-q", "q-lambda")


def _f(default, help: str):
    return field(default=default, metadata={"help": help})


@dataclass
class TrainConfig:
    """All training hyperparameters; `asdict(cfg)` is stored in meta.json."""

    map: str = _f("paper10", "built-in map name, generator spec (e.g. trap-16x16-s0) or path to a .map file")
    encoding: str = _f("cell", "state encoding: cell (robot cell x goal), sector (kinematic twin) or sector-memory "
                                   "(sector x Bug-style wall-following mode, direct setting)")
    targets: str = _f("", "comma-separated target names or col:row cells (cell encoding); empty = all map targets")
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
    sector_guidance: str = _f("path", "sector: path = steer to the ground station's planned waypoints (ground_station/maps/planner.py; "
                                      "the robot gets them as a mission), direct = steer to the goal's bearing only")
    sector_bearing_sectors: int = _f(15, "sector: goal-bearing sectors (odd: no sector straddles straight behind)")
    sector_sensors: str = _f("0,1,7", "sector: comma-separated range sensor indices in the state")
    sector_range_edges: str = _f("100,400", "sector: comma-separated ascending range bin edges (mm)")
    sector_margin_mm: float = _f(75.0, "sector: clearance beyond the robot radius a pruned waypoint segment keeps")
    sector_max_segment_mm: float = _f(1000.0, "sector: longest waypoint segment (mm); 0 = no limit")
    sector_align_reward: float = _f(1.0, "sector: shaping reward per pi rad the target's bearing turns toward ahead")
    sector_progress_reward: float = _f(1.0, "sector: reward per cell of progress along the guide potential "
                                            "(remaining waypoint path, or the goal's octile field when direct)")
    sector_reverse_cost: float = _f(0.02, "sector: extra cost per control period spent reversing "
                                          "(the robot has no rear range sensor in the state)")
    sector_hold_max: int = _f(100, "sector: control periods a chosen action is held while the state is unchanged, "
                                   "learnt as one semi-Markov transition; 1 = plain one-step updates")
    sector_lr_end: float = _f(0.005, "sector: learning rate at the last step (linear from --lr); = --lr for a constant rate")
    sector_range_noise_mm: float = _f(10.0, "sector: std (mm) of Gaussian noise on the range readings the learner sees "
                                            "(the sim's sensor noise); 0 = exact readings")
    sector_maps: str = _f("", "sector: extra comma-separated training maps (names or generator specs) besides --map")
    grid_free_mm: int = _f(350, "sector-memory: a neighbour cell counts as free when the range sensor looking at it "
                                "reads at least this (mm; 100 mm = the cell's own wall, >= 600 mm = the next cell free)")
    grid_leave_margin_mm: int = _f(1, "sector-memory: leave the wall once the goal is this much closer than where it was hit")
    grid_wall_bearing: int = _f(0, "sector-memory: 1 = the wall modes' state includes the goal sector too")
    grid_wall_cost: float = _f(0.0, "sector-memory: shaping cost per move in a wall mode that ends with the "
                                    "followed side's neighbour free (the wall lost)")
    grid_go_reward: float = _f(0.0, "sector-memory: shaping reward in the go mode per cell the straight-line "
                                    "goal distance falls")
    q_init_scale: float = _f(0.0, "initial Q values uniform in [-scale, scale] (the paper initialises randomly); 0 = zeros")
    curve_points: int = _f(200, "number of episode windows in the learning curve")
    chunk_steps: int = _f(1_000_000, "steps per kernel call (progress bar granularity)")


# The shipped recipe of an encoding: the TrainConfig fields that differ from
# the dataclass defaults (the cell encoding's recipe is the defaults). `qnav
# train --encoding E` starts from RECIPES[E]; flags given on the command line
# override it; `qnav train --recipe NAME` names one (SHIPPED_RECIPES: the
# policies/ files, with map paper10 and seed 0 as the defaults;
# docs/training.md).
RECIPES: dict[str, dict[str, Any]] = {
    "cell": {},
    "sector": {"steps": 20_000_000, "lr": 0.1, "gamma": 0.95, "reward_step": 0.0, "epsilon_end": 0.05},
    # cell-stepped Bug memory (docs/training.md, "Sector state with memory"): paper10 plus generated maps of
    # seeds 0 (random) and 10 (maze, rooms, trap), never the evaluation's seeds 1 and 2; the wall-keeping cost
    "sector-memory": {"steps": 10_000_000, "lr": 0.1, "gamma": 0.95, "epsilon_end": 0.05,
                           "sector_maps": "random-16x16-s0,random-16x16-s1,maze-16x16-s10,rooms-16x16-s10,"
                                          "trap-16x16-s10", "grid_wall_cost": 0.02},
}
SHIPPED_RECIPES = {"shipped-cell": "cell", "shipped-sector": "sector", "shipped-sector-memory": "sector-memory"}


def recipe_config(encoding: str, given: dict[str, Any]) -> TrainConfig:
    """TrainConfig from the encoding's recipe, then `given` (explicit values win)."""
    return TrainConfig(**{**RECIPES.get(encoding, {}), **given, "encoding": encoding})


ENCODINGS = ("cell", "sector", "sector-memory")
# sector fields the sector-memory trainer reads too (its extra maps, its learning-rate schedule, the
# planner's waypoints it starts from)
_SECTOR_FIELDS_OF_MEMORY = {"sector_maps", "sector_lr_end", "sector_margin_mm", "sector_max_segment_mm"}
_LEARNER_FIELDS = {"learner_lambda", "trace_min", "dyna_planning"}  # cell and sector only (sector-memory: q)


def applies_to(name: str) -> tuple[str, ...]:
    """The encodings whose training reads TrainConfig field `name` (its --help section)."""
    if name == "targets":
        return ("cell",)
    if name in _LEARNER_FIELDS:
        return ("cell", "sector")
    if name.startswith("sector_"):
        return ("sector", "sector-memory") if name in _SECTOR_FIELDS_OF_MEMORY else ("sector",)
    if name.startswith("grid_"):
        return ("sector-memory",)
    return ENCODINGS


_GROUPS = {ENCODINGS: "training (every encoding)", ("cell",): "cell encoding",
           ("cell", "sector"): "learners other than q (cell and sector encodings)",
           ("sector",): "sector encoding", ("sector", "sector-memory"): "sector and sector-memory encodings",
           ("sector-memory",): "sector-memory encoding"}


def add_config_arguments(parser: argparse.ArgumentParser, skip: tuple[str, ...] = ()) -> None:
    """One `--flag` per TrainConfig field, with the field's help text, grouped by the encodings
    that read it (`applies_to`)."""
    groups: dict[tuple[str, ...], argparse._ArgumentGroup] = {}
    for f in fields(TrainConfig):
        if f.name in skip:
            continue
        where = applies_to(f.name)
        if where not in groups:
            groups[where] = parser.add_argument_group(_GROUPS[where])
        flag = "--" + f.name.replace("_", "-")
        kind = type(f.default)
        groups[where].add_argument(flag, type=int_arg if kind is int else kind, default=f.default, dest=f.name,
                                   help=f"{f.metadata.get('help', '')} (default: {f.default})")


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


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    return TrainConfig(**{f.name: getattr(args, f.name) for f in fields(TrainConfig) if hasattr(args, f.name)})


def validate_config(cfg: TrainConfig) -> None:
    """Raise ValueError (one line) on an impossible configuration."""
    if cfg.encoding not in ENCODINGS:
        raise ValueError(f"encoding must be one of {', '.join(ENCODINGS)}, got {cfg.encoding!r}")
    if cfg.learner not in LEARNERS:
        raise ValueError(f"learner must be one of {', '.join(LEARNERS)}, got {cfg.learner!r}")
    if cfg.learner != "q" and cfg.encoding == "sector-memory":
        raise ValueError(f"learner {cfg.learner} is implemented for the cell and sector encodings "
                         "(sector-memory training: q)")
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
    if cfg.encoding == "sector":
        _check_sector(cfg)
    if cfg.encoding == "sector-memory":
        from firmware_py.gridbug import GridBugEncoder

        if cfg.grid_wall_bearing not in (0, 1):
            raise ValueError(f"grid_wall_bearing must be 0 or 1, got {cfg.grid_wall_bearing}")
        if not 0.0 <= cfg.sector_lr_end <= 1.0:
            raise ValueError(f"sector_lr_end must be in [0, 1], got {cfg.sector_lr_end}")
        GridBugEncoder(free_mm=cfg.grid_free_mm, leave_margin_mm=cfg.grid_leave_margin_mm)  # its own checks
    if cfg.max_episode_steps < 0 or cfg.curve_points < 1 or cfg.chunk_steps < 1:
        raise ValueError("max_episode_steps must be >= 0, curve_points and chunk_steps >= 1")


def int_list(text: str, name: str) -> tuple[int, ...]:
    """'1,2,3' -> (1, 2, 3); ValueError naming the field otherwise."""
    try:
        return tuple(int(v) for v in str(text).split(",") if v.strip())
    except ValueError:
        raise ValueError(f"{name} must be comma-separated integers, got {text!r}") from None


def _check_sector(cfg: TrainConfig) -> None:
    if cfg.sector_guidance not in ("path", "direct"):
        raise ValueError(f"sector_guidance must be path or direct, got {cfg.sector_guidance!r}")
    if cfg.sector_hold_max < 1:
        raise ValueError(f"sector_hold_max must be >= 1, got {cfg.sector_hold_max}")
    if not 0.0 <= cfg.sector_lr_end <= 1.0:
        raise ValueError(f"sector_lr_end must be in [0, 1], got {cfg.sector_lr_end}")
    if cfg.sector_margin_mm < 0 or cfg.sector_max_segment_mm < 0 or cfg.sector_range_noise_mm < 0:
        raise ValueError("sector_margin_mm, sector_max_segment_mm and sector_range_noise_mm must be >= 0")
    if not int_list(cfg.sector_sensors, "sector_sensors"):
        raise ValueError("sector_sensors must name at least one sensor")
    int_list(cfg.sector_range_edges, "sector_range_edges")


def recipe_defaults(parser: argparse.ArgumentParser) -> None:
    """Leave the recipe fields (and --encoding) unset on a parser built with
    `add_config_arguments`, so that `config_from_recipe_args` can tell a flag
    left out (it takes the encoding's recipe) from one given."""
    parser.set_defaults(encoding=None, **{k: None for r in RECIPES.values() for k in r})


def config_from_recipe_args(args: argparse.Namespace, encoding: str | None = None) -> TrainConfig:
    """TrainConfig from parsed flags, recipe-aware (`qnav train`, `sweep`, `study`):
    the encoding (`encoding`, else --encoding, else cell) picks RECIPES[encoding];
    a flag given (not None) wins over it, a flag left out takes it, else the
    TrainConfig default."""
    given = {f.name: getattr(args, f.name) for f in fields(TrainConfig)
             if getattr(args, f.name, None) is not None and f.name != "encoding"}
    return recipe_config(encoding or getattr(args, "encoding", None) or "cell", given)
