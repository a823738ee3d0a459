"""The robot profile (firmware_py/profile.py): the shipped examples load, bad files are refused with
one line naming the file and the key (qnav-robot exits 2), and a policy trained for another geometry is
refused naming both values."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from firmware_py import robot_spec
from firmware_py.policy import config_mismatch, load_policy
from firmware_py.profile import DEFAULT, ProfileError, geometry_mismatch, load_profile
from firmware_py.shipped_policies import shipped_policy

ROOT = Path(__file__).resolve().parents[2]
PROFILES = sorted((ROOT / "firmware_py" / "profiles").glob("*.toml"))


def test_every_shipped_profile_loads_and_the_default_is_the_built_in_robot():
    assert {p.stem for p in PROFILES} >= {"qnav", "odrive"}
    for path in PROFILES:
        prof = load_profile(path)
        assert prof.source == str(path)
    assert DEFAULT.geometry.wheel_base_mm == robot_spec.WHEEL_BASE_MM
    assert DEFAULT.policy_geometry()["sensor_angles_mrad"] == list(robot_spec.SENSOR_ANGLES_MRAD)
    assert load_profile(ROOT / "firmware_py" / "profiles" / "qnav.toml").policy_geometry() == DEFAULT.policy_geometry()


@pytest.mark.parametrize("text, where, words", [
    ("[drive]\nbackend = 'vesc'\n", "drive.backend", "expected one of qnav, odrive, dronecan"),
    ("[drive]\nleft_sign = 2\n", "drive.left_sign", "expected 1 or -1"),
    ("[drive]\nbackend = 'odrive'\nleft_node = 40\n", "drive.left_node", "expected 0..31"),
    ("[drive]\nleft_node = 3\nright_node = 3\n", "drive.right_node", "the same as left_node"),
    ("[geometry]\nwheel_base_mm = -5\n", "geometry.wheel_base_mm", "expected 1..100000"),
    ("[geometry]\nwheel_base_mm = 'wide'\n", "geometry.wheel_base_mm", "expected an integer"),
    ("[geometry]\nwheelbase = 260\n", "geometry.wheelbase", "unknown key"),
    ("[motors]\n", "[motors]", "unknown section"),
    ("[sensors]\nangles_deg = [0, 90]\n", "sensors.angles_deg", "2 sensors; expected 3..16"),
    ("[sensors]\nangles_deg = [0, 60, 120, 180, -120, -60]\n", "sensors.angles_deg",
     "qnav's RangeSectors frames carry exactly 8"),
    ("[sensors]\nbackend = \"dronecan\"\nangles_deg = [0, 90, 180]\nmax_ranges_mm = [1000, 2000]\n",
     "sensors.max_ranges_mm", "2 ranges for 3 sensors"),
    ("[boards]\nbumper = 1\n", "boards.bumper", "expected true or false"),
    ("[sensors]\nmax_range_mm = nan\n", "sensors.max_range_mm", "expected an integer"),
    ("[drive\n", "not valid TOML", ""),
])
def test_a_bad_profile_is_one_line_naming_the_file_and_the_key(tmp_path, text, where, words):
    f = tmp_path / "robot.toml"
    f.write_text(text)
    with pytest.raises(ProfileError) as err:
        load_profile(f)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(str(f)) and where in msg and words in msg


def test_qnav_robot_exits_2_on_a_bad_profile_naming_file_and_key(tmp_path):
    f = tmp_path / "robot.toml"
    f.write_text("[drive]\nright_sign = 0\n")
    run = subprocess.run([Path(sys.executable).parent / "qnav-robot", "--profile", f, "--mavlink", "none",
                          "--can", "virtual:x", "--duration", "0.1"], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    assert f"--profile {f}: drive.right_sign: expected 1 or -1, got 0" in run.stderr


def test_a_policy_trained_for_another_geometry_is_refused_naming_both_values(tmp_path):
    pol = load_policy(shipped_policy("sector"))
    wide = tmp_path / "wide.toml"
    wide.write_text("[geometry]\nwheel_base_mm = 400\n")
    prof = load_profile(wide)
    why = config_mismatch(pol, pol.control_period_us, 500, None, prof)
    assert why == f"policy trained for wheel_base_mm 260, robot profile {wide} has 400"
    assert config_mismatch(pol, pol.control_period_us, 500, None, DEFAULT) == ""
    # a recorded geometry is compared key by key
    assert geometry_mismatch({**DEFAULT.policy_geometry(), "max_range_mm": 4000}, DEFAULT) == (
        "policy trained for max_range_mm 4000, robot profile built-in default has 2000")
