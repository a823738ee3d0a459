"""Plant profiles (sim_bridge/profiles.py) and the encoder scale error they set."""

import math
import random

import numpy as np
import pytest

from firmware_py import robot_spec
from sim_bridge.cli import main
from sim_bridge.plant import Plant, SimConfig
from sim_bridge.profiles import PROFILES, PlantProfile
from sim_bridge.sensors import WheelEncoders
from sim_bridge.world import Pose, World

DT = robot_spec.PHYSICS_DT_US / 1e6


def test_scale_error_makes_one_encoder_read_long():
    world = World(np.zeros((4, 8), bool), 0.5, Pose(0.5, 1.0, 0.0))
    enc = WheelEncoders(world, random.Random(0), scale=(1.03, 1.0))
    for _ in range(round(2.0 / DT)):
        world.drive(0.5, 0.5)
        enc.integrate(DT)
        world.step(DT)
    left, right = enc.counts()
    per_m = robot_spec.ENCODER_TICKS_PER_REV / (2 * math.pi * robot_spec.WHEEL_RADIUS_MM / 1000)
    assert right == pytest.approx((world.pose.x - 0.5) * per_m, abs=3)
    assert left == pytest.approx(1.03 * right, abs=3)


def test_profile_reaches_the_plant():
    prof = PROFILES["realistic"]
    assert prof != PROFILES["ideal"]
    plant = Plant(np.zeros((4, 4), bool), SimConfig.from_profile(prof, seed=3), Pose(1.0, 1.0, 0.0))
    assert plant.encoders.scale == prof.encoder_scale and plant.encoders.slip_std == prof.slip_std
    assert plant.ranges.p.noise_std_mm == prof.range_noise_mm and plant.ranges.p.dropout == prof.range_dropout
    with pytest.raises(ValueError, match="outside 0.5..1.5"):
        PlantProfile("x", encoder_scale=(2.0, 1.0))


@pytest.mark.parametrize("argv, why", [
    (["--profile", "nope"], "unknown plant profile 'nope'"),
    (["--enc-scale-left", "0"], "encoder scale (0.0, 1.0) outside 0.5..1.5"),
    (["--dropout", "2"], "dropout in [0, 1]"),
])
def test_bad_profile_options_are_one_line_errors(argv, why, capsys):
    assert main(["--map", "paper10", "--can", "virtual:x", "--duration", "0.1", *argv]) == 2
    err = capsys.readouterr().err
    assert why in err and err.count("\n") == 1


def test_help_gives_every_profile_value_from_profiles(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    for name, prof in PROFILES.items():
        for value in (prof.range_noise_mm, prof.range_dropout, prof.slip_std, *prof.encoder_scale):
            assert f"{name}: {value:g}" in text
