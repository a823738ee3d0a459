"""The robot a training run is for (`qnav train --profile FILE.toml`), what the run records of it
(meta.json `robot`) and the check that it can run what the encoding reads (`firmware_py.needs`).
Kept apart from `ground_station.learn.config` so the kinds' option checks can use it without an
import cycle."""

from __future__ import annotations

from typing import Any


def training_profile(cfg: Any) -> Any:
    """The robot profile a config trains for (`firmware_py.profile.RobotProfile`), None for the built-in
    robot; ProfileError (a ValueError, one line naming the file and the key) if it cannot be read."""
    if not cfg.profile:
        return None
    from firmware_py.profile import load_profile

    return load_profile(cfg.profile)


def trained_for(cfg: Any) -> Any:
    """The robot a config's policy is trained for (`firmware_py.needs.TrainedFor`)."""
    from firmware_py.needs import TrainedFor

    return TrainedFor.of_profile(training_profile(cfg))


def check_profile_fits(cfg: Any, encoder: Any) -> None:
    """ValueError (one line) when the robot `cfg.profile` cannot run what `encoder` reads (a sector no
    sensor covers, a sensor too short for the encoder's range edges, a body its free test does not
    work for): the robot would refuse the policy (firmware_py.needs), so it is not trained."""
    profile = training_profile(cfg)
    if profile is None:
        return
    from firmware_py import kinds as robot_kinds
    from firmware_py import robot_spec
    from firmware_py.needs import TrainedFor, needs_mismatch, policy_needs

    need = policy_needs(robot_kinds.of_name(encoder.kind), encoder, TrainedFor.of_profile(profile),
                        robot_spec.CONTROL_PERIOD_US)
    why = needs_mismatch(need, profile)
    if why:
        raise ValueError(f"--profile {cfg.profile}: the {encoder.kind} encoding cannot run on this robot: {why}")
