"""The policies shipped in policies/: they load with the robot's loader,
match what tools/make_policy.py recorded beside them, still drive as
recorded, and the cell one regenerates to the same policy id."""

import json
import shlex

import numpy as np
import pytest

from firmware_py.policy import load_policy
from firmware_py.shipped_policies import shipped_policies_dir
from ground_station.cli import main

POLICIES = shipped_policies_dir()
SHIPPED = sorted(POLICIES.glob("*.qtab"))


def int_table(pol) -> np.ndarray:
    return np.array(pol.table.tolist(), dtype=np.float64).reshape(pol.n_states, pol.n_actions)


def test_the_paper10_cell_policy_ships():
    assert POLICIES / "paper10_cell.qtab" in SHIPPED


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_shipped_file_matches_its_record(path):
    rec = json.loads(path.with_suffix(".json").read_text())
    pol = load_policy(path)
    assert f"0x{pol.policy_id:08x}" == rec["policy_id"]
    assert f"0x{pol.crc:08x}" == rec["crc32"]
    assert pol.size == rec["bytes"] == path.stat().st_size
    assert (pol.kind, pol.dtype, pol.n_states) == (rec["encoding"], rec["dtype"], rec["n_states"])
    assert pol.metadata["quantisation"]["dtype"] == rec["dtype"]
    assert pol.metadata["map"] == rec["map"]
    readme = (POLICIES / "README.md").read_text()
    assert path.name in readme and f"tools/make_policy.py {path.stem}" in readme


def test_paper10_cell_policy_reaches_a_to_d_optimally_as_recorded():
    from ground_station.learn.cell.evaluate import evaluate_cell
    from ground_station.maps import load_map

    path = POLICIES / "paper10_cell.qtab"
    rec = json.loads(path.with_suffix(".json").read_text())
    pol = load_policy(path)
    gm = load_map("paper10")
    assert pol.metadata["targets"] == ["A", "B", "C", "D"]
    assert list(pol.goals) == [gm.targets[t] for t in "ABCD"]
    rep = evaluate_cell(int_table(pol), gm, list(pol.goals))
    assert rep["success_rate"] == rec["success_rate"]["int"] == rec["success_rate"]["float"] == 1.0
    assert rep["path_ratio_mean"] == rec["path_ratio_mean"]["int"] == rec["path_ratio_mean"]["float"] == 1.0


def test_paper10_cell_policy_regenerates_to_the_same_policy_id(tmp_path, capsys):
    rec = json.loads((POLICIES / "paper10_cell.json").read_text())
    train = shlex.split(rec["commands"][0])[1:]
    train[train.index("--out") + 1] = str(tmp_path / "run")
    assert main(train) == 0
    out = tmp_path / "p.qtab"
    assert main(["export", str(tmp_path / "run"), "--dtype", rec["dtype"], "--out", str(out), "--no-rollouts"]) == 0
    capsys.readouterr()
    assert f"0x{load_policy(out).policy_id:08x}" == rec["policy_id"]


def test_inspect_prints_the_shipped_header(capsys):
    assert main(["policy", "inspect", *map(str, SHIPPED)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(SHIPPED)
    for path, line in zip(SHIPPED, lines, strict=True):
        rec = json.loads(path.with_suffix(".json").read_text())
        assert line.startswith(f"{path}: valid v2.0 {rec['encoding']}") and rec["policy_id"] in line


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_shipped_policy_records_the_robots_period_and_its_training_map(path):
    from firmware_py import robot_spec
    from firmware_py.policy import config_mismatch
    from firmware_py.vehicle import VehicleConfig
    from ground_station.maps import load_map

    pol = load_policy(path)
    gm = load_map(pol.metadata["map"])
    assert pol.control_period_us == robot_spec.CONTROL_PERIOD_US == VehicleConfig().control_period_us
    assert pol.map_geometry == (round(gm.cell_size_m * 1000), gm.width, gm.height)
    cfg = VehicleConfig()
    assert config_mismatch(pol, cfg.control_period_us, cfg.cell_size_mm) == ""  # the default robot runs it


def test_sector_policy_drives_as_recorded_and_int8_is_within_half_a_point_of_float():
    from ground_station.learn.sector.evaluate import evaluate_sector
    from ground_station.maps import load_map

    path = POLICIES / "sector.qtab"
    rec = json.loads(path.with_suffix(".json").read_text())
    pol = load_policy(path)
    args = shlex.split(rec["commands"][1])
    sample, seed = int(args[args.index("--sample") + 1]), int(args[args.index("--seed") + 1])
    rep = evaluate_sector(int_table(pol), load_map(rec["map"]), pol.encoder, sample=sample, seed=seed)
    assert rep["episodes"] == rec["episodes"] == sample
    assert rep["success_rate"] == rec["success_rate"]["int"]
    assert abs(rec["success_rate"]["int"] - rec["success_rate"]["float"]) <= 0.005


def test_sector_memory_policy_drives_as_recorded_in_the_direct_setting():
    """The cell-stepped Bug memory table: every (start, goal, heading) of
    paper10 on the grid twin, as its .json records (the acceptance figure:
    >= 0.95, no collision), and int8 within 0.5 points of float."""
    from ground_station.learn.sector_memory.trainer import evaluate_gridbug
    from ground_station.maps import load_map

    path = POLICIES / "sector_memory.qtab"
    rec = json.loads(path.with_suffix(".json").read_text())
    pol = load_policy(path)
    assert pol.kind == "sector-memory" and pol.metadata["config"]["encoding"] == "sector-memory"
    rep = evaluate_gridbug(int_table(pol), load_map(rec["map"]), pol.encoder)
    assert rep["episodes"] == rec["episodes"] == 75 * 74 * 8
    assert rep["success_rate"] == rec["success_rate"]["int"] >= 0.95
    assert rep["collisions"] == rec["collisions"]["int"] == 0
    assert abs(rec["success_rate"]["int"] - rec["success_rate"]["float"]) <= 0.005
