"""Greedy evaluation of a saved training run, whatever its kind: the run folder is read
once and judged by its kind's evaluation (`ground_station.learn.kinds`), with the
baselines that kind reports beside the policy (`qnav eval`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ground_station.learn import kinds
from ground_station.learn.export import TrainingRun, load_run
from ground_station.maps import GridMap

__all__ = ["evaluate_run", "evaluate_table", "on_robot", "plot_run"]


def evaluate_table(q, run: TrainingRun, gridmap: GridMap, *, sample: int | None = None,  # type: ignore[no-untyped-def]
                   seed: int = 0, full: bool = False) -> dict:
    """Greedy rollouts of table `q` (the run's, or its quantised copy) with the run's encoder."""
    kind = kinds.of_name(run.encoder.kind)
    rep: dict = kinds.resolve(kind.evaluate)(q, run, gridmap, sample=sample, seed=seed, full=full)
    rep.setdefault("encoding", kind.name)
    rep.setdefault("map", gridmap.name)
    return rep


def evaluate_run(run_dir: str | Path, gridmap: GridMap, sample: int | None = None, seed: int = 0,
                 profile: Any = None) -> dict:
    """Evaluate a saved run on `gridmap` with its kind's evaluation and baselines; the twin plays the
    robot the run was trained for, or `profile` (a `firmware_py.profile.RobotProfile`) if given."""
    run = load_run(run_dir)
    if profile is not None:
        run = on_robot(run, profile)
    return evaluate_table(run.q, run, gridmap, sample=sample, seed=seed, full=True)


def on_robot(run: TrainingRun, profile: Any) -> TrainingRun:
    """`run` judged on another robot: its meta.json `robot` replaced by the profile's (what the kinds'
    evaluations play, `twin.TwinRobot.of_meta`)."""
    from dataclasses import replace

    from firmware_py.needs import TrainedFor

    return replace(run, meta={**run.meta, "robot": TrainedFor.of_profile(profile).to_dict()})


def plot_run(run_dir: str | Path, gridmap: GridMap) -> bytes:
    """PNG of a run's greedy policy, for the kinds that draw one (ValueError otherwise)."""
    run = load_run(run_dir)
    kind = kinds.of_name(run.encoder.kind)
    if kind.plot is None:
        raise ValueError(f"--plot draws a policy per cell; the {kind.name} kind has no such plot")
    return bytes(kinds.resolve(kind.plot)(run.q, run, gridmap))
