"""`qnav policy inspect` and `qnav export` from the command line."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from firmware_py import robot_spec
from firmware_py.kinds.cell.encoder import CellEncoder
from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.policy import HEADER, HEADER_V1, MapGeometry, load_policy
from firmware_py.storage import ftp_crc32
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
                                 SectorEncoder(), map_geometry=MapGeometry(500, 12, 8), control_period_us=40_000))
    bad = tmp_path / "bad.qtab"
    bad.write_bytes(good.read_bytes()[:-1])
    return good, sec, bad


def test_inspect_prints_one_header_line_per_file_and_exit_0(files, capsys):
    good, sec, _ = files
    assert main(["policy", "inspect", str(good), str(sec)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2
    pol = load_policy(good)
    assert lines[0].startswith(f"{good}: valid v2.0 cell width=10 height=10 n_goals=2 goals=")
    assert "period_us=50000 map=10x10x500mm" in lines[0] and "period_us=40000 map=12x8x500mm" in lines[1]
    assert f"id=0x{pol.policy_id:08x}" in lines[0] and f"policy CRC 0x{pol.crc:08x}" in lines[0]
    assert f"file CRC32 0x{ftp_crc32(good.read_bytes()):08x}" in lines[0]
    assert 'targets=["A", "B"]' in lines[0] and "int8 200x4" in lines[0]
    assert "sector bearing_sectors=8" in lines[1] and "int16 1944x4" in lines[1]


def test_inspect_json_and_exit_2_when_any_file_is_invalid(files, capsys):
    good, _, bad = files
    assert main(["policy", "inspect", "--json", str(good), str(bad), str(good.parent / "nope")]) == 2
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["valid"] for r in rows] == [True, False, False]
    assert rows[0]["error"] is None and rows[0]["n_states"] == 200 and rows[0]["goals"] == [[0, 0], [9, 9]]
    assert rows[0]["crc32"] == f"0x{load_policy(good).crc:08x}"
    assert rows[0]["control_period_us"] == robot_spec.CONTROL_PERIOD_US
    assert rows[0]["map_geometry"] == {"cell_mm": 500, "width": 10, "height": 10}
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


def test_export_keeps_the_float_argmax_by_default_and_rounds_only_when_told(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", "--map", "paper10", "--encoding", "cell", "--targets", "A", "--steps", "20000",
                 "--seed", "0", "--out", str(run), "--quiet"]) == 0
    q = np.load(run / "q.npy")
    lsb = np.abs(q).max() / 127
    q[0] = [10.0 * lsb, 10.3 * lsb, 0.0, 0.0]  # a unique float best (1) that rounding ties with forward (0)
    np.save(run / "q.npy", q)
    capsys.readouterr()
    untied, rounded = tmp_path / "untied.qtab", tmp_path / "rounded.qtab"
    assert main(["export", str(run), "--no-rollouts", "--out", str(untied)]) == 0
    assert json.loads(capsys.readouterr().out)["argmax_fixes"] >= 1
    assert main(["export", str(run), "--no-rollouts", "--no-preserve-argmax", "--out", str(rounded)]) == 0
    assert json.loads(capsys.readouterr().out)["argmax_fixes"] == 0
    assert load_policy(untied).best_action(0) == 1 and load_policy(rounded).best_action(0) == 0


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
    # the header records the twin's period and the training map (paper10) of a sector run
    assert pol.control_period_us == robot_spec.CONTROL_PERIOD_US and pol.map_geometry == (500, 10, 10)


def as_version_1(b: bytes) -> bytes:
    """The same policy as a format 1.0 file (48-byte header, no period or geometry)."""
    import zlib

    fields = list(HEADER.unpack_from(b, 0))[:14]
    fields[1], fields[2], fields[3] = 1, 0, HEADER_V1.size
    body = HEADER_V1.pack(*fields) + b[HEADER.size:-4]
    return body + zlib.crc32(body).to_bytes(4, "little")


def test_upgrade_migrates_version_1_files_atomically_and_inspect_then_accepts_them(files, tmp_path, capsys):
    good, sec, _ = files
    old_cell, old_sec = tmp_path / "old_cell.qtab", tmp_path / "old_sec.qtab"
    old_cell.write_bytes(as_version_1(good.read_bytes()))
    sector_v2 = sec.read_bytes()
    old_sec.write_bytes(as_version_1(sector_v2))
    assert main(["policy", "inspect", str(old_cell)]) == 2
    assert "records no control period" in capsys.readouterr().out
    # a cell policy's geometry is its grid; in place, atomically
    assert main(["policy", "upgrade", str(old_cell), "--control-period-us", "50000"]) == 0
    assert json.loads(capsys.readouterr().out)["format_version"] == "2.0"
    assert old_cell.read_bytes() == good.read_bytes()
    assert sorted(f.name for f in tmp_path.iterdir() if f.name.startswith("old_")) == ["old_cell.qtab", "old_sec.qtab"]
    # a sector policy without a map in its metadata needs --map; nothing is written on refusal
    assert main(["policy", "upgrade", str(old_sec), "--control-period-us", "40000"]) == 2
    err = capsys.readouterr().err
    assert "names no training map" in err and len(err.strip().splitlines()) == 1
    assert old_sec.read_bytes() == as_version_1(sector_v2)
    new = tmp_path / "new_sec.qtab"
    assert main(["policy", "upgrade", str(old_sec), "--out", str(new), "--control-period-us", "40000",
                 "--map", "paper10"]) == 0
    row = json.loads(capsys.readouterr().out)
    assert row["control_period_us"] == 40_000 and row["map_geometry"] == {"cell_mm": 500, "width": 10, "height": 10}
    assert new.read_bytes()[HEADER.size:-4] == sector_v2[HEADER.size:-4]  # table and the rest copied
    assert load_policy(new).policy_id == load_policy(sec).policy_id
    # a current file has nothing to upgrade
    assert main(["policy", "upgrade", str(new), "--control-period-us", "40000"]) == 2
    assert "nothing to upgrade" in capsys.readouterr().err
