"""The robot's own map (qnav-robot --map FILE; issue 30 item 4): read from a MovingAI file with its
errors named by line, and a policy carrying another map refused at boot and at activation, naming
both, so a 10x10 policy on a robot in a 16x16 world is not accepted and then driven into walls."""

from __future__ import annotations

import subprocess
import sys

import pytest

from firmware_py.control.controller import Controller
from firmware_py.mapdata import MapDataError, grid_from_map_file
from firmware_py.policy import load_policy
from firmware_py.shipped_policies import shipped_policy
from firmware_py.vehicle import VehicleConfig


def _write(tmp_path, rows, name="world.map"):
    path = tmp_path / name
    path.write_text(f"type octile\nheight {len(rows)}\nwidth {len(rows[0])}\nmap\n" + "\n".join(rows) + "\n")
    return path


def test_map_file_is_read_and_its_errors_are_named_by_line(tmp_path):
    grid = grid_from_map_file(str(_write(tmp_path, ["..@", "S.T"])), 500)
    assert (grid.width, grid.height, grid.occ) == (3, 2, bytes([0, 0, 1, 0, 0, 1]))
    with pytest.raises(MapDataError, match=r"bad.map:6: unknown character '#'"):
        grid_from_map_file(str(_write(tmp_path, ["...", ".#."], "bad.map")), 500)
    with pytest.raises(MapDataError, match="cannot read"):
        grid_from_map_file(str(tmp_path / "none.map"), 500)


def test_a_policy_for_another_map_is_refused_at_activation_naming_both(tmp_path):
    ctrl = Controller(VehicleConfig())
    ctrl.robot_map = grid_from_map_file(str(_write(tmp_path, ["." * 16] * 16)), 500)
    ok, why = ctrl.activate_policy(str(shipped_policy("sector")))
    assert not ok and why == "policy map paper10 (10x10 cells of 500 mm) is not the robot's map (16x16 cells of 500 mm)"
    assert ctrl.policy is None
    paper10 = load_policy(shipped_policy("sector")).map_grid
    ctrl.robot_map = paper10  # the right world: accepted
    assert ctrl.activate_policy(str(shipped_policy("sector"))) == (True, "")


def test_qnav_robot_refuses_at_boot_in_one_line(tmp_path):
    world = _write(tmp_path, ["." * 16] * 16)
    run = subprocess.run([sys.executable, "-m", "firmware_py.cli", "--policy", "policies:sector", "--map", str(world),
                          "--can", "virtual:robot-map-test", "--duration", "0.1", "--mavlink", "none"],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and run.stderr.strip().count("\n") == 0, run.stderr
    assert "is not the robot's map (16x16 cells of 500 mm)" in run.stderr
