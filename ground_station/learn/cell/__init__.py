"""The `cell` kind's training: the paper's grid state (robot cell x goal), its
Q-learning kernel (`trainer`), the other tabular learners (`learners`) and its
greedy evaluation against BFS shortest paths (`evaluate`).

This module is the kind's front door for the registry (`ground_station.learn.kinds`):
its options and `KIND`, without numba."""

from __future__ import annotations

from dataclasses import dataclass

from firmware_py.kinds.cell.encoder import CellEncoder
from ground_station.learn.kinds import TrainingKind, option

LEARNERS = ("q", "sarsa", "expected-sarsa", "double-q", "dyna-q", "q-lambda")


@dataclass
class CellOptions:
    """What only cell training reads."""

    targets: str = option("", "comma-separated target names or col:row cells; empty = all map targets")


def encoder_from_dict(d: dict) -> CellEncoder:
    return CellEncoder(width=int(d["width"]), height=int(d["height"]), n_goals=int(d.get("n_goals", 1)))


KIND = TrainingKind(
    name="cell", summary="robot cell x goal (the paper's state)", options=CellOptions, prefix="",
    train="ground_station.learn.cell.trainer:train_cell",
    evaluate="ground_station.learn.cell.evaluate:evaluate_policy",
    plot="ground_station.learn.cell.evaluate:plot_policy", encoder_from_dict=encoder_from_dict, learners=LEARNERS,
    sweep_sample=20_000)
