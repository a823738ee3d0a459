"""Symmetric quantiser and the float-vs-int comparison (ground_station.learn.export)."""

import json

import numpy as np
import pytest

from firmware_py.atomic import atomic_write
from firmware_py.kinds.cell.encoder import CellEncoder
from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.policy import MapGeometry, load_policy
from ground_station.lab.bench.campaign import float_table
from ground_station.learn.export import (
    Quantised,
    compare,
    encoder_from_dict,
    file_metadata,
    load_run,
    policy_bytes,
    quantise,
    tie_rate,
)


def dequantise(qt: Quantised) -> np.ndarray:
    """The floats `qt` stands for: its table times its scale (or each row's own)."""
    s = qt.state_scales[:, None].astype(np.float64) if qt.state_scales is not None else qt.scale
    return qt.table.astype(np.float64) * s


def test_one_scale_per_table_maps_the_peak_to_qmax():
    q = np.array([[1.0, -2.0, 0.5, 0.0], [0.25, 0.0, 0.0, -0.1]])
    qt = quantise(q, "int8")
    assert qt.scale == pytest.approx(2.0 / 127)
    assert qt.table.dtype == np.int8
    assert qt.table[0].tolist() == [64, -127, 32, 0]  # 63.5 -> 64 (half to even), 31.75 -> 32
    assert qt.rounding_ties == 1
    assert np.max(np.abs(dequantise(qt) - q)) <= qt.scale / 2 + 1e-12
    q16 = quantise(q, "int16")
    assert q16.table.dtype == np.int16 and q16.table[0, 1] == -32767


def test_rounding_ties_are_counted_and_round_half_to_even():
    q = np.array([[127.0, 0.5, 1.5, -2.5]])  # scale 1: three exact halves
    qt = quantise(q, "int8")
    assert qt.scale == 1.0
    assert qt.table[0].tolist() == [127, 0, 2, -2]
    assert qt.rounding_ties == 3


def test_preserve_argmax_unties_only_rows_whose_float_argmax_is_unique():
    # scale 1: row 0's float argmax (left, 83.4) ties forward (82.6) after rounding, and the robot's
    # lowest-index tie-break would drive forward; row 1 ties in the float table too (left alone);
    # row 2 needs nothing; row 3 ties at the floor (the best goes up 1 LSB instead)
    q = np.array([[82.6, 83.4, 56.0, 59.0], [10.0, 10.0, 3.0, 0.0], [127.0, 0.0, 1.0, 2.0],
                  [-126.8, -127.0, -127.0, -127.0]])
    plain = quantise(q, "int8")
    assert plain.table[0].tolist() == [83, 83, 56, 59] and compare(q, plain)["argmax_agreement"] == 0.75  # row 3: the tie-break happens to agree
    qt = quantise(q, "int8", preserve_argmax=True)
    assert qt.table[0].tolist() == [82, 83, 56, 59]
    assert qt.table[1].tolist() == [10, 10, 3, 0]
    assert qt.table[2].tolist() == [127, 0, 1, 2]
    assert qt.table[3].tolist() == [-126, -127, -127, -127]
    assert qt.argmax_fixes == 2 and qt.table.dtype == np.int8
    c = compare(q, qt)
    assert c["argmax_agreement"] == 1.0 and c["argmax_fixes"] == 2 and c["tie_rate"] == c["float_tie_rate"] == 0.25
    assert np.max(np.abs(dequantise(qt) - q)) <= 1.5 * qt.scale  # at most one LSB beyond rounding's half
    per = quantise(q * 0.01, "int8", per_state=True, preserve_argmax=True)
    assert compare(q * 0.01, per)["argmax_agreement"] == 1.0


def test_per_state_scales_keep_small_rows_apart():
    q = np.array([[100.0, 0.0, 0.0, 0.0], [0.010, 0.011, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    one = quantise(q, "int8")
    per = quantise(q, "int8", per_state=True)
    assert one.table[1].tolist() == [0, 0, 0, 0]  # collapsed to a tie
    assert per.table[1].tolist() == [115, 127, 0, 0]
    assert per.state_scales.dtype == np.float32 and per.state_scales[2] == 1.0  # all-zero row
    assert compare(q, per)["argmax_agreement"] == 1.0
    assert compare(q, one)["argmax_agreement"] == pytest.approx(2 / 3)
    assert compare(q, one)["tie_rate"] == pytest.approx(2 / 3)
    assert compare(q, one)["float_tie_rate"] == pytest.approx(1 / 3)
    assert np.allclose(dequantise(per), q, atol=1e-3)


def test_quantise_refuses_bad_tables():
    for bad in (np.zeros((0, 4)), np.zeros(4), np.array([[np.nan, 0, 0, 0]])):
        with pytest.raises(ValueError):
            quantise(bad)
    with pytest.raises(ValueError):
        quantise(np.zeros((1, 4)), "int4")
    qt = quantise(np.zeros((2, 4)))
    assert qt.scale == 1.0 and tie_rate(qt.table) == 1.0


def test_policy_bytes_round_trip_equals_quantised_table():
    rng = np.random.default_rng(0)
    enc = SectorEncoder(4, (0, 1, 7), (300, 900))
    q = rng.normal(size=(enc.n_states, 4)) * 50
    for dtype in ("int8", "int16"):
        for per in (False, True):
            qt = quantise(q, dtype, per_state=per)
            p = load_policy(policy_bytes(qt, enc, metadata={"k": 1}, map_geometry=MapGeometry(500, 10, 10)))
            assert np.array_equal(np.array(p.table.tolist()).reshape(q.shape), qt.table)
            assert p.scale == pytest.approx(qt.scale)
            assert np.allclose(float_table(p), dequantise(qt), rtol=1e-6)
    with pytest.raises(ValueError):
        policy_bytes(quantise(q[:-1]), enc)


def make_run(tmp_path, enc, goals=None, **meta):
    q = np.random.default_rng(1).normal(size=(enc.n_states, enc.n_actions))
    np.save(tmp_path / "q.npy", q)
    m = {"encoding": enc.kind, "encoder": enc.to_dict(), "map": "paper10", "targets": ["A"],
         "config": {"lr": 0.5}, "steps": 1000, "train_seconds": 0.1, "created": "2026-01-02T03:04:05Z"}
    if goals is not None:
        m["goals"] = goals
    m.update(meta)
    (tmp_path / "meta.json").write_text(json.dumps(m))
    return q


def test_load_run_reads_the_training_contract(tmp_path):
    enc = CellEncoder(10, 10, 1)
    q = make_run(tmp_path, enc, goals=[[2, 3]])
    run = load_run(tmp_path)
    assert run.encoder == enc and run.goals == [(2, 3)] and np.array_equal(run.q, q)
    meta = file_metadata(run, quantise(run.q))
    assert meta["map"] == "paper10" and meta["quantisation"] == {"dtype": "int8", "per_state_scales": False}
    assert encoder_from_dict(SectorEncoder().to_dict()) == SectorEncoder()


def test_load_run_errors_are_one_line(tmp_path):
    with pytest.raises(ValueError, match="not a training run"):
        load_run(tmp_path)
    make_run(tmp_path, CellEncoder(10, 10, 2), goals=[[2, 3]])
    with pytest.raises(ValueError, match="1 goals for 2"):
        load_run(tmp_path)
    np.save(tmp_path / "q.npy", np.zeros((3, 4)))
    with pytest.raises(ValueError, match="shape"):
        load_run(tmp_path)


def test_atomic_write_replaces_whole_file(tmp_path):
    p = tmp_path / "x.qtab"
    atomic_write(p, b"old")
    atomic_write(p, b"new contents")
    assert p.read_bytes() == b"new contents"
    assert [f.name for f in tmp_path.iterdir()] == ["x.qtab"]
