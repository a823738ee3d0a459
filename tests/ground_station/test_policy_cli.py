"""`qnav policy inspect` and `qnav export` from the command line."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from firmware_py.encoders import CellEncoder, SectorEncoder
from firmware_py.policy import load_policy
from ground_station.cli import main
from ground_station.learn.export import policy_bytes, quantise

QNAV = [sys.executable, "-m", "ground_station.cli"]


@pytest.fixture()
def files(tmp_path):
    rng = np.random.default_rng(5)
    cell = CellEncoder(10, 10, 2)
    good = tmp_path / "good.qtab"
    good.write_bytes(policy_bytes(quantise(rng.normal(size=(200, 4))), cell, goals=[(0, 0), (9, 9)],
                                  metadata={"map": "paper10", "targets": ["A", "B"]}))
    sec = tmp_path / "sector.qtab"
    sec.write_bytes(policy_bytes(quantise(rng.normal(size=(SectorEncoder().n_states, 4)), "int16"),
                                 SectorEncoder()))
    bad = tmp_path / "bad.qtab"
    bad.write_bytes(good.read_bytes()[:-1])
    return good, sec, bad


def test_inspect_prints_one_header_line_per_file_and_exit_0(files, capsys):
    good, sec, _ = files
    assert main(["policy", "inspect", str(good), str(sec)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    pol = load_policy(good)
    assert lines[0].startswith(f"{good}: valid v1.0 cell 10x10")
    assert f"id=0x{pol.policy_id:08x}" in lines[0] and f"crc=0x{pol.crc:08x}" in lines[0]
    assert 'targets=["A", "B"]' in lines[0] and "int8 200x4" in lines[0]
    assert "sector bearing_sectors=8" in lines[1] and "int16 1944x4" in lines[1]


def test_inspect_json_and_exit_2_when_any_file_is_invalid(files, capsys):
    good, _, bad = files
    assert main(["policy", "inspect", "--json", str(good), str(bad), str(good.parent / "nope")]) == 2
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["valid"] for r in rows] == [True, False, False]
    assert rows[0]["error"] is None and rows[0]["n_states"] == 200 and rows[0]["goals"] == [[0, 0], [9, 9]]
    assert rows[0]["crc32"] == f"0x{load_policy(good).crc:08x}"
    assert "truncated" in rows[1]["error"] and rows[1]["file"] == str(bad)
    assert "cannot read" in rows[2]["error"]


def test_inspect_against_a_robot_with_fewer_sensors(files, capsys):
    _, sec, _ = files
    assert main(["policy", "inspect", "--sensors", "4", str(sec)]) == 2
    assert "sensor" in capsys.readouterr().out


def test_console_script_exit_status(files):
    good, _, bad = files
    ok = subprocess.run([*QNAV, "policy", "inspect", str(good)], capture_output=True, text=True, timeout=60)
    assert ok.returncode == 0 and "valid" in ok.stdout
    ko = subprocess.run([*QNAV, "policy", "inspect", str(bad)], capture_output=True, text=True, timeout=60)
    assert ko.returncode == 2 and "INVALID" in ko.stdout


def test_export_trained_cell_run_int8_drives_like_float(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", "--map", "paper10", "--encoding", "cell", "--targets", "A,B,C,D",
                 "--steps", "3000000", "--seed", "0", "--out", str(run), "--quiet"]) == 0
    capsys.readouterr()
    out = tmp_path / "p.qtab"
    assert main(["export", str(run), "--dtype", "int8", "--out", str(out)]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["bytes"] == out.stat().st_size and rep["dtype"] == "int8"
    assert rep["success_rate"] == {"float": 1.0, "int": 1.0}
    assert rep["path_ratio_mean"] == {"float": 1.0, "int": 1.0}
    assert 0.0 <= rep["tie_rate"] <= 1.0 and rep["argmax_agreement"] > 0.9
    pol = load_policy(out)
    meta = json.loads((run / "meta.json").read_text())
    assert pol.goals == tuple(tuple(g) for g in meta["goals"])
    assert pol.metadata["targets"] == ["A", "B", "C", "D"] and pol.metadata["map"] == "paper10"
    assert rep["policy_id"] == f"0x{pol.policy_id:08x}"
    q = np.load(run / "q.npy")
    assert [pol.best_action(s) for s in range(pol.n_states)] == \
        np.argmax(quantise(q, "int8").table, axis=1).tolist()


def test_export_errors_are_one_line_and_leave_no_file(tmp_path, capsys):
    out = tmp_path / "x.qtab"
    assert main(["export", str(tmp_path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "not a training run" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_export_per_state_int16_without_rollouts(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("SOURCE_DATE_EPOCH", raising=False)
    enc = SectorEncoder(4, (0, 2), (500,))
    q = np.random.default_rng(2).normal(size=(enc.n_states, 4))
    np.save(tmp_path / "q.npy", q)
    (tmp_path / "meta.json").write_text(json.dumps({"encoding": "sector", "encoder": enc.to_dict(),
                                                    "map": "paper10", "created": 1234}))
    out = tmp_path / "s.qtab"
    assert main(["export", str(tmp_path), "--dtype", "int16", "--per-state-scale", "--no-rollouts",
                 "--policy-id", "0xbeef", "--out", str(out)]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["argmax_agreement"] == 1.0 and rep["per_state_scales"] is True and "success_rate" not in rep
    pol = load_policy(Path(out))
    assert pol.policy_id == 0xBEEF and pol.created == 1234 and pol.state_scales is not None
