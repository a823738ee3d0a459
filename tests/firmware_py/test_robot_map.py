"""The robot's own map (qnav-robot --map FILE, qnav map upload; issues 30 and 32): read from a MovingAI
file with its errors named by line; a cell policy (its table indexed by one map's cells) for another
map refused at boot and at activation, naming both, so a 10x10 table is not driven into the walls of
a 16x16 world; a sector policy localises and plans on the robot's map whatever map its file carries."""

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


def test_a_cell_policy_for_another_map_is_refused_naming_both_and_a_sector_policy_takes_the_robots(tmp_path):
    ctrl = Controller(VehicleConfig())
    world = grid_from_map_file(str(_write(tmp_path, ["." * 16] * 16)), 500)
    assert ctrl.set_robot_map(world) == (True, "map 16x16 cells of 500 mm active")
    ok, why = ctrl.activate_policy(str(shipped_policy("paper10_cell")))
    assert not ok and why.startswith("policy map paper10 (10x10 cells of 500 mm") and why.endswith(
        "is not the robot's map (16x16 cells of 500 mm)")
    assert ctrl.policy is None
    assert ctrl.activate_policy(str(shipped_policy("sector"))) == (True, "")  # not map-specific
    assert ctrl.policy is not None and ctrl.policy.map_grid == world  # it localises and plans on the robot's
    assert load_policy(shipped_policy("sector")).map_grid != world
    paper10 = load_policy(shipped_policy("paper10_cell")).map_grid
    assert ctrl.set_robot_map(paper10)[0] and ctrl.policy.map_grid == paper10  # a new map: the policy follows
    assert ctrl.activate_policy(str(shipped_policy("paper10_cell"))) == (True, "")  # its own world: accepted
    ok, why = ctrl.set_robot_map(world)  # and now the 16x16 map is refused: the cell table is tied to paper10
    assert not ok and "is not the robot's map (16x16 cells of 500 mm)" in why and ctrl.robot_map == paper10


def test_qnav_robot_refuses_at_boot_in_one_line(tmp_path):
    world = _write(tmp_path, ["." * 16] * 16)
    run = subprocess.run([sys.executable, "-m", "firmware_py.cli", "--policy", "policies:paper10_cell", "--map", str(world),
                          "--can", "virtual:robot-map-test", "--duration", "0.1", "--mavlink", "none"],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and run.stderr.strip().count("\n") == 0, run.stderr
    assert "is not the robot's map (16x16 cells of 500 mm)" in run.stderr
