"""One profile, every stage (issue 44): `qnav train --profile` trains every encoding for the profile's
robot (the twin plays its body, wheel base, wheel speed limit and the policy's sectors as its sensors
read them), `qnav eval --profile` judges a run on a robot's twin, `qnav export` records what the
policy needs of the robot and `--profile` refuses a robot that cannot run it; the built-in robot is
the default profile, bit for bit."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from firmware_py.needs import NEEDS_KEY
from firmware_py.policy import config_mismatch, load_policy
from firmware_py.profile import load_profile
from ground_station.cli import main
from ground_station.learn.config import recipe_config
from ground_station.learn.sector import twin as T
from ground_station.learn.sector.trainer import SectorTrainer, sector_encoder
from ground_station.maps import load_map

ROOT = Path(__file__).resolve().parents[2]
WIDE = ROOT / "firmware_py" / "profiles" / "wide_six.toml"
BUILT_IN = ROOT / "firmware_py" / "profiles" / "qnav.toml"


def test_the_built_in_profile_is_the_default_twin_and_trains_the_same_table():
    built_in = T.TwinRobot.of_profile(load_profile(BUILT_IN)).arrays()
    for a, b in zip(built_in, T.DEFAULT_TW, strict=True):
        assert np.array_equal(a, b)
    tables = []
    for profile in ("", str(BUILT_IN)):
        cfg = recipe_config("sector", {"map": "paper10", "steps": 60_000, "seed": 3, "profile": profile})
        tr = SectorTrainer([load_map("paper10")], cfg, sector_encoder(cfg))
        q = np.zeros((tr.n_states, tr.n_actions))
        tr.run(q, 0, cfg.steps)
        tables.append(q)
    assert np.array_equal(tables[0], tables[1]) and np.any(tables[0] != 0)


def test_the_twin_plays_the_profiles_body_wheel_base_and_sensors():
    wide = T.TwinRobot.of_profile(load_profile(WIDE))
    tw = wide.arrays()
    occ = np.zeros((6, 6), dtype=np.uint8)
    occ[:, 4] = 1  # a wall whose face is at x = 2000 mm
    # facing the wall from 1500 mm: the front sensor reads from the 180 mm rim
    r, st = T.sense_one(occ, 6, 6, 500.0, 1500.0, 1500.0, 0.0, 0, tw)
    assert (r, st) == (500 - 180, 1)
    r0, _ = T.sense_one(occ, 6, 6, 500.0, 1500.0, 1500.0, 0.0, 0, T.DEFAULT_TW)
    assert r0 == 500 - 150
    # sector 45 deg is read by the sensor at 40 deg, sector 135 deg by none (INVALID, as the robot reads it)
    assert wide.angles_mrad[1] == round(math.radians(40) * 1000)
    assert T.sense_one(occ, 6, 6, 500.0, 1500.0, 1500.0, 0.0, 3, tw) == (0, 0)
    # a turn action at 320 mm/s differential turns at 320 / wheel base
    _, _, th, _, _ = T.move(occ, 6, 6, 500.0, 1000.0, 1500.0, 0.0, 1, tw)
    assert th == pytest.approx(320 / 320 * 0.05)
    _, _, th0, _, _ = T.move(occ, 6, 6, 500.0, 1000.0, 1500.0, 0.0, 1, T.DEFAULT_TW)
    assert th0 == pytest.approx(320 / 260 * 0.05)
    # the body: driving at the wall stops 180 mm short of it, not 150
    x = 1000.0
    for _ in range(60):  # 20 mm a period
        x, _, _, _, hit = T.move(occ, 6, 6, 500.0, x, 1500.0, 0.0, 0, tw)
        if hit:
            break
    assert hit and 2000 - 180 < x <= 2000 - 180 + 2  # the first 2 mm substep that overlaps


def _train(tmp_path, name, *args):
    out = tmp_path / name
    assert main(["train", *args, "--out", str(out), "--quiet"]) == 0
    return out


@pytest.mark.parametrize("encoding, steps", [("cell", "20000"), ("sector", "40000"), ("sector-memory", "20000")])
def test_every_encoding_trains_for_a_profile_and_exports_what_it_needs(tmp_path, capsys, encoding, steps):
    run = _train(tmp_path, "run", "--encoding", encoding, "--profile", str(WIDE), "--steps", steps)
    meta = json.loads((run / "meta.json").read_text())
    assert meta["robot"]["source"] == "wide_six.toml" and meta["robot"]["robot_radius_mm"] == 180
    assert meta["config"]["profile"] == str(WIDE)
    out = tmp_path / "p.qtab"
    assert main(["export", str(run), "--out", str(out), "--no-rollouts", "--profile", str(WIDE)]) == 0
    pol = load_policy(out)
    need = pol.metadata[NEEDS_KEY]
    assert need["trained_for"] == "wide_six.toml" and need["wheel_speed_mm_s"] == 400
    assert config_mismatch(pol, pol.control_period_us, 500, None, load_profile(WIDE)) == ""
    capsys.readouterr()
    assert main(["policy", "inspect", str(out)]) == 0
    line = capsys.readouterr().out
    assert "robot_needs: trained for: wide_six.toml" in line and "wheel speed: 400 mm/s" in line
    if encoding == "sector":
        assert "sector 45 deg: a sensor within 10 deg of 40 deg reaching 400 mm" in line
        assert need["robot_radius_mm_max"] == 180 and need["wheel_base_mm"] == [288, 352]
    if encoding == "cell":
        assert "sectors" not in need  # a cell policy reads no sensor
        # the built-in robot runs it (grid moves): only the period and the wheel speed count
        assert config_mismatch(pol, pol.control_period_us, 500, None, None) == ""


def test_a_policy_for_one_robot_is_refused_by_another_naming_both_values(tmp_path, capsys):
    run = _train(tmp_path, "wide", "--recipe", "shipped-sector", "--profile", str(WIDE), "--steps", "20000")
    out = tmp_path / "w.qtab"
    assert main(["export", str(run), "--out", str(out), "--no-rollouts"]) == 0
    pol = load_policy(out)
    why = config_mismatch(pol, pol.control_period_us, 500, None, load_profile(BUILT_IN))
    assert why == f"policy trained for wheel_base_mm 288..352, robot profile {BUILT_IN} has 260"
    capsys.readouterr()
    assert main(["export", str(run), "--out", str(tmp_path / "x.qtab"), "--no-rollouts",
                 "--profile", str(BUILT_IN)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"qnav export: error: --profile {BUILT_IN}: {why}" and not (tmp_path / "x.qtab").exists()


def test_training_refuses_a_profile_that_cannot_read_the_encoders_sectors(tmp_path, capsys):
    # sector 135 deg (index 3) has no sensor on the six-sensor robot
    assert main(["train", "--encoding", "sector", "--sector-sensors", "0,3", "--profile", str(WIDE),
                 "--steps", "1000", "--out", str(tmp_path / "r"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"qnav train: error: --profile {WIDE}: the sector encoding cannot run on this robot: policy "
                   f"reads sector 135 deg, robot profile {WIDE} has no sensor within 22.5 deg of it "
                   "(sensors at 0, 40, -50, 95, -85, 180 deg)"]
    big = tmp_path / "big.toml"
    big.write_text("[geometry]\nrobot_radius_mm = 260\n")
    assert main(["train", "--encoding", "sector-memory", "--profile", str(big), "--steps", "1000",
                 "--out", str(tmp_path / "r2"), "--quiet"]) == 2
    assert "policy trained for robot_radius_mm 249 at most" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text("[geometry]\nwheel_base_mm = -1\n")
    assert main(["train", "--profile", str(bad), "--steps", "10", "--out", str(tmp_path / "r3")]) == 2
    assert capsys.readouterr().err.strip() == (f"qnav train: error: {bad}: geometry.wheel_base_mm: "
                                               "expected 1..100000, got -1")


def test_eval_plays_the_profile_it_is_given(tmp_path, capsys):
    run = _train(tmp_path, "built_in", "--recipe", "shipped-sector", "--steps", "200000")
    reps = []
    for extra in ([], ["--profile", str(WIDE)]):
        assert main(["eval", str(run), "--sample", "300", "--json", *extra]) == 0
        reps.append(json.loads(capsys.readouterr().out))
    # the same table on a wider, slower-turning robot with sensors elsewhere drives differently
    assert reps[0]["episodes"] == reps[1]["episodes"] == 300
    assert (reps[0]["success_rate"], reps[0]["collisions"]) != (reps[1]["success_rate"], reps[1]["collisions"])
