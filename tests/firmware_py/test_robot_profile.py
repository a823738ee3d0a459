"""The robot profile (firmware_py/profile.py): the shipped examples load, bad files are refused with
one line naming the file and the key (qnav-robot exits 2), and a policy whose needs a robot does not
meet (firmware_py.needs) is refused naming both values."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from firmware_py import robot_spec
from firmware_py.policy import config_mismatch, load_policy
from firmware_py.profile import DEFAULT, ProfileError, load_profile
from firmware_py.shipped_policies import shipped_policy

ROOT = Path(__file__).resolve().parents[2]
PROFILES = sorted((ROOT / "firmware_py" / "profiles").glob("*.toml"))


def test_every_shipped_profile_loads_and_the_default_is_the_built_in_robot():
    assert {p.stem for p in PROFILES} >= {"qnav", "odrive"}
    for path in PROFILES:
        prof = load_profile(path)
        assert prof.source == str(path)
    assert DEFAULT.geometry.wheel_base_mm == robot_spec.WHEEL_BASE_MM
    assert DEFAULT.layout().angles_mrad == robot_spec.SENSOR_ANGLES_MRAD
    assert load_profile(ROOT / "firmware_py" / "profiles" / "qnav.toml").layout() == DEFAULT.layout()


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


def test_a_policy_is_refused_by_a_robot_that_does_not_meet_its_needs_naming_both_values(tmp_path):
    """The shipped sector policy has no record: it was trained for the built-in robot. A wider base, a
    bigger body, another wheel speed or its sectors' sensors missing refuse it; the example profiles
    with the built-in geometry (dronecan, odrive) run it."""
    pol = load_policy(shipped_policy("sector"))

    def why(text: str) -> str:
        f = tmp_path / "robot.toml"
        f.write_text(text)
        return config_mismatch(pol, pol.control_period_us, 500, None, load_profile(f)).replace(str(f), "R")

    assert why("[geometry]\nwheel_base_mm = 400\n") == "policy trained for wheel_base_mm 234..286, robot profile R has 400"
    assert why("[geometry]\nwheel_base_mm = 280\n") == ""  # within 10 %: the turn rate within 10 %
    assert why("[geometry]\nrobot_radius_mm = 180\n") == ("policy trained for robot_radius_mm 150 at most, robot "
                                                          "profile R has 180")
    assert why("[drive]\nmax_speed_mm_s = 300\n") == ("policy trained for wheel speed 400 mm/s, robot profile R "
                                                      "drives 300 mm/s (drive.max_speed_mm_s 300)")
    assert why("[sensors]\nbackend = 'dronecan'\nangles_deg = [0, 90, 180, -90, -45, 135]\n") == (
        "policy reads sector 45 deg, robot profile R has no sensor within 22.5 deg of it (sensors at "
        "0, 90, 180, -90, -45, 135 deg)")
    assert why("[sensors]\nangles_deg = [20, 45, 90, 135, 180, -135, -90, -45]\n") == (
        "policy trained with sector 0 deg read at 0 deg, robot profile R reads it at 20 deg (more than 10 deg apart)")
    assert why("[sensors]\nmax_ranges_mm = [300, 2000, 2000, 2000, 2000, 2000, 2000, 2000]\n") == (
        "policy reads sector 0 deg to 400 mm, robot profile R's sensor there reaches 300 mm")
    # the sensors it does not read may be anywhere, listed in any order
    assert why("[sensors]\nangles_deg = [-45, 0, 45, 100, 170, -120, -80, 120]\n") == ""
    for name in ("dronecan", "odrive", "qnav"):
        assert config_mismatch(pol, pol.control_period_us, 500, None,
                               load_profile(ROOT / "firmware_py" / "profiles" / f"{name}.toml")) == ""
    assert config_mismatch(pol, pol.control_period_us, 500, None, DEFAULT) == ""


def test_the_older_robot_geometry_record_is_read_as_what_the_policy_was_trained_for():
    from dataclasses import replace

    from firmware_py.needs import NEEDS_KEY, needs_mismatch, needs_of

    pol = load_policy(shipped_policy("sector"))
    old = {"wheel_base_mm": 320, "robot_radius_mm": 180, "max_range_mm": 2000,
           "sensor_angles_mrad": list(robot_spec.SENSOR_ANGLES_MRAD)}
    # a file written before the needs record: the older geometry record only (the shipped table, re-exported
    # at b35b992, carries the newer record, which wins)
    meta = {k: v for k, v in pol.metadata.items() if k != NEEDS_KEY}
    need = needs_of(replace(pol, metadata={**meta, "robot_geometry": old}))
    assert need["robot_radius_mm_max"] == 180 and need["wheel_base_mm"] == [288, 352]
    assert needs_mismatch(need, DEFAULT) == ("policy trained for wheel_base_mm 288..352, robot profile built-in "
                                             "default has 260")
