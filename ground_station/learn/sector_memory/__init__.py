"""The `sector-memory` kind's training: the cell-stepped Bug memory on a grid twin
(`kernels`: the jitted encoder copy, the Q-learning and rollout kernels) and its
trainer, hand-written baseline and greedy evaluation (`trainer`).

This module is the kind's front door for the registry (`ground_station.learn.kinds`):
its options, their checks and `KIND`, without numba."""

from __future__ import annotations

from dataclasses import dataclass

from firmware_py import robot_spec
from firmware_py.kinds.sector_memory.gridbug import GridBugEncoder
from ground_station.learn.kinds import TrainingKind, option


@dataclass
class SectorMemoryOptions:
    """What only sector-memory training reads (flags --grid-*, and the sector flags it shares)."""

    free_mm: int = option(350, "a neighbour cell counts as free when the range sensor looking at it reads at "
                               "least this (mm; 100 mm = the cell's own wall, >= 600 mm = the next cell free)")
    leave_margin_mm: int = option(1, "leave the wall once the goal is this much closer than where it was hit")
    wall_bearing: int = option(0, "1 = the wall modes' state includes the goal sector too")
    wall_cost: float = option(0.0, "shaping cost per move in a wall mode that ends with the followed side's "
                                   "neighbour free (the wall lost)")
    go_reward: float = option(0.0, "shaping reward in the go mode per cell the straight-line goal distance falls")
    lr_end: float = option(0.005, "learning rate at the last step (linear from --lr); = --lr for a constant rate",
                           flag="sector_lr_end")
    maps: str = option("", "extra comma-separated training maps (names or generator specs) besides --map",
                       flag="sector_maps")


def encoder_of(options: SectorMemoryOptions) -> GridBugEncoder:
    """The robot's encoder these options ask for (ValueError with its own checks)."""
    return GridBugEncoder(free_mm=int(options.free_mm), leave_margin_mm=int(options.leave_margin_mm),
                          wall_bearing=bool(options.wall_bearing), cell_mm=robot_spec.DEFAULT_CELL_SIZE_MM)


def validate(cfg) -> None:  # type: ignore[no-untyped-def]
    o: SectorMemoryOptions = cfg.options
    if o.wall_bearing not in (0, 1):
        raise ValueError(f"grid_wall_bearing must be 0 or 1, got {o.wall_bearing}")
    if not 0.0 <= o.lr_end <= 1.0:
        raise ValueError(f"sector_lr_end must be in [0, 1], got {o.lr_end}")
    from ground_station.learn.robot import check_profile_fits

    check_profile_fits(cfg, encoder_of(o))


def encoder_from_dict(d: dict) -> GridBugEncoder:
    return GridBugEncoder(free_mm=int(d["free_mm"]), leave_margin_mm=int(d["leave_margin_mm"]),
                          cell_mm=int(d["cell_mm"]), wall_bearing=bool(d["wall_bearing"]))


# paper10 plus generated maps of seeds 0 (random) and 10 (maze, rooms, trap), never the
# evaluation's seeds 1 and 2; the wall-keeping cost (docs/training.md)
KIND = TrainingKind(
    name="sector-memory", summary="sector x Bug-style wall-following mode, cell-stepped, direct setting",
    options=SectorMemoryOptions, prefix="grid_",
    train="ground_station.learn.sector_memory.trainer:train_sector_memory",
    evaluate="ground_station.learn.sector_memory.trainer:evaluate_policy", encoder_from_dict=encoder_from_dict,
    validate=validate,
    recipe={"steps": 10_000_000, "lr": 0.1, "gamma": 0.95, "epsilon_end": 0.05,
            "sector_maps": "random-16x16-s0,random-16x16-s1,maze-16x16-s10,rooms-16x16-s10,trap-16x16-s10",
            "grid_wall_cost": 0.02})
