"""`.qtab` format: byte layout, round trip and the loader's field checks."""

import json
import math
import random
import struct
import zlib
from array import array

import numpy as np
import pytest

from firmware_py import robot_spec
from firmware_py.kinds.base import best_action
from firmware_py.kinds.cell.encoder import CellEncoder
from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.policy import (
    CRC,
    HEADER,
    HEADER_V1,
    MAGIC,
    MAX_FILE_BYTES,
    MAX_METADATA_BYTES,
    MapGeometry,
    PolicyError,
    config_mismatch,
    dump_policy,
    load_policy,
    upgrade_policy,
)
from ground_station.lab.bench.campaign import float_table
from ground_station.learn.export import compare, policy_bytes, quantise

GOALS = [(1, 1), (8, 2), (3, 7), (9, 9)]
PAPER10 = MapGeometry(500, 10, 10)  # a sector policy's training map


def cell_file(**kw) -> bytes:
    enc = CellEncoder(10, 10, 4)
    rng = random.Random(1)
    table = array("b", [rng.randint(-127, 127) for _ in range(enc.n_states * enc.n_actions)])
    args = {"goals": GOALS, "metadata": {"map": "paper10"}, "created": 1_700_000_000}
    args.update(kw)
    return dump_policy(enc, table, "int8", 0.25, **args)


def fix_crc(b: bytes | bytearray) -> bytes:
    body = bytes(b[:-4])
    return body + CRC.pack(zlib.crc32(body))


def set_field(b: bytes, index: int, value) -> bytes:
    fields = list(HEADER.unpack_from(b, 0))
    fields[index] = value
    return fix_crc(HEADER.pack(*fields) + b[HEADER.size:])


def as_version_1(b: bytes) -> bytes:
    """The same policy as a format 1.0 file: the 48-byte header, no period or geometry."""
    fields = list(HEADER.unpack_from(b, 0))[:14]
    fields[1], fields[2], fields[3] = 1, 0, HEADER_V1.size
    return fix_crc(HEADER_V1.pack(*fields) + b[HEADER.size:])


def test_header_layout_is_byte_exact():
    b = cell_file(policy_id=0x01020304)
    assert b[:4] == b"QTAB"
    assert b[4] == 2 and b[5] == 0  # major, minor
    assert struct.unpack_from("<H", b, 6)[0] == 58  # header_size
    assert struct.unpack_from("<I", b, 8)[0] == 0  # flags
    assert b[12] == 1 and b[13] == 1  # kind cell, dtype int8
    assert struct.unpack_from("<HI", b, 14) == (4, 400)
    assert b[20:24] == bytes([4, 3, 2, 1])  # little-endian policy id
    assert struct.unpack_from("<q", b, 24)[0] == 1_700_000_000
    assert struct.unpack_from("<d", b, 32)[0] == 0.25
    enc_len, meta_len = struct.unpack_from("<II", b, 40)
    # control period (u32 us), map geometry (u16 cell mm, u16 width, u16 height)
    assert struct.unpack_from("<IHHH", b, 48) == (robot_spec.CONTROL_PERIOD_US, 500, 10, 10)
    # cell section: 4 x u16 head + 4 goals x 2 u16 + 4 actions x 2 i16
    assert enc_len == 8 + 4 * 4 + 4 * 4
    assert struct.unpack_from("<HHHH", b, 58) == (10, 10, 4, robot_spec.DEFAULT_CELL_SIZE_MM)
    assert struct.unpack_from("<HH", b, 66) == (1, 1)
    meta = b[58 + enc_len:58 + enc_len + meta_len]
    assert json.loads(meta) == {"map": "paper10"}
    assert len(b) == 58 + enc_len + meta_len + 400 * 4 + 4
    assert struct.unpack_from("<I", b, len(b) - 4)[0] == zlib.crc32(b[:-4])


def test_round_trip_cell_and_sector_both_dtypes():
    for enc in (CellEncoder(10, 10, 4), SectorEncoder(), SectorEncoder(4, (0, 2), (500,))):
        for dtype, lo, hi in (("int8", -127, 127), ("int16", -32767, 32767)):
            rng = random.Random(enc.n_states)
            vals = [rng.randint(lo, hi) for _ in range(enc.n_states * enc.n_actions)]
            goals = GOALS if enc.kind == "cell" else ()
            geometry = None if enc.kind == "cell" else PAPER10
            b = dump_policy(enc, vals, dtype, 0.5, goals=goals, metadata={"x": [1, 2]}, control_period_us=40_000,
                            map_geometry=geometry)
            p = load_policy(b)
            assert p.control_period_us == p.header()["control_period_us"] == 40_000
            assert p.map_geometry == (PAPER10 if enc.kind == "sector" else MapGeometry(500, 10, 10))
            assert p.header()["map_geometry"] == p.map_geometry._asdict()
            assert p.encoder == enc and p.dtype == dtype and p.kind == enc.kind
            assert isinstance(p.table, memoryview) and p.table.readonly
            assert p.table.tolist() == vals
            assert p.n_states == enc.n_states and p.n_actions == enc.n_actions
            assert p.crc == zlib.crc32(b[:-4]) and p.size == len(b)
            assert p.metadata == {"x": [1, 2]}
            if enc.kind == "cell":
                assert p.goals == tuple(GOALS) and p.cell_mm == robot_spec.DEFAULT_CELL_SIZE_MM
            for s in range(0, enc.n_states, 7):
                row = vals[s * enc.n_actions:(s + 1) * enc.n_actions]
                assert list(p.row(s)) == row
                assert p.best_action(s) == best_action(row)


def test_best_action_ties_break_to_lowest_index_like_the_ground_station():
    enc = CellEncoder(3, 1, 1)
    rows = [[5, 5, 1, 0], [-2, 3, 3, 3], [0, 0, 0, 0]]
    p = load_policy(dump_policy(enc, [v for r in rows for v in r], "int16", 1.0, goals=[(0, 0)]))
    assert [p.best_action(s) for s in range(3)] == [0, 1, 0]
    assert [p.best_action(s) for s in range(3)] == np.argmax(np.array(rows), axis=1).tolist()
    with pytest.raises(IndexError):
        p.row(3)
    with pytest.raises(IndexError):
        p.best_action(-1)


def test_quantised_table_robot_argmax_equals_numpy_argmax_on_every_state():
    rng = np.random.default_rng(3)
    enc = SectorEncoder()
    q = rng.normal(size=(enc.n_states, 4)).round(1)  # rounding makes ties
    for per_state in (False, True):
        qt = quantise(q, "int8", per_state=per_state)
        p = load_policy(policy_bytes(qt, enc, map_geometry=PAPER10))
        robot_side = [p.best_action(s) for s in range(enc.n_states)]
        assert robot_side == np.argmax(qt.table, axis=1).tolist()
        assert compare(q, qt)["tie_rate"] > 0  # the case the tie rule matters for


def test_policy_id_defaults_to_content_and_ignores_metadata_and_time():
    a = load_policy(cell_file(metadata={"a": 1}, created=5))
    b = load_policy(cell_file(metadata={"b": 2}, created=6))
    assert a.policy_id == b.policy_id and a.crc != b.crc
    assert load_policy(cell_file(policy_id=7)).policy_id == 7


def test_per_state_scales_round_trip_and_float_table():
    enc = CellEncoder(2, 1, 1)
    b = dump_policy(enc, [1, 2, 3, 4, -4, 0, 0, 0], "int8", 2.0, state_scales=[0.5, 2.0], goals=[(0, 0)])
    p = load_policy(b)
    assert p.header()["per_state_scales"] is True
    assert float_table(p).tolist() == [[0.5, 1.0, 1.5, 2.0], [-8.0, 0.0, 0.0, 0.0]]


@pytest.mark.parametrize("index,value,reason", [
    (0, b"QTAX", "magic"),
    (1, 3, "version 3.0 unsupported"),
    (1, 0, "version 0.0 unsupported"),
    (1, 1, r"version 1.0 records no control period or map geometry; migrate it with `qnav policy upgrade"),
    (3, 57, "header_size"),
    (4, 0x2, "unknown flag"),
    (5, 9, "encoder kind"),
    (6, 3, "dtype"),
    (7, 5, "actions"),
    (8, 401, "declare"),
    (8, 0, "no states"),
    (8, 2**32 - 1, "declare"),
    (10, -1, "negative"),
    (11, 0.0, "scale"),
    (11, -1.0, "scale"),
    (11, math.nan, "scale"),
    (11, math.inf, "scale"),
    (12, 2**32 - 1, "declare"),
    (13, MAX_METADATA_BYTES + 1, "metadata"),
    (14, 0, "control period is 0"),
    (15, 0, "zero field"),
    (16, 0, "zero field"),
    (17, 0, "zero field"),
    (15, 250, r"header map geometry 10x10 cells of 250 mm differs from the cell encoder's 10x10 cells of 500 mm"),
    (17, 11, "differs from the cell encoder's"),
])
def test_each_header_field_is_checked(index, value, reason):
    with pytest.raises(PolicyError, match=reason):
        load_policy(set_field(cell_file(), index, value))


def test_newer_minor_version_with_a_longer_header_is_read():
    b = cell_file()
    fields = list(HEADER.unpack_from(b, 0))
    fields[2] = 7  # minor
    fields[3] = HEADER.size + 8  # 8 bytes of fields this loader does not know
    newer = fix_crc(HEADER.pack(*fields) + b"\xaa" * 8 + b[HEADER.size:])
    p = load_policy(newer)
    assert p.version == (2, 7)
    assert p.table.tolist() == load_policy(b).table.tolist()


def test_robot_configuration_is_enforced():
    enc = SectorEncoder(4, (0, 7), (500,))
    b = dump_policy(enc, [0] * enc.n_states * 4, "int8", 1.0, map_geometry=PAPER10)
    assert load_policy(b).encoder.sensors == (0, 7)
    with pytest.raises(PolicyError, match="sensor index 7"):
        load_policy(b, expect_sensors=6)
    with pytest.raises(PolicyError, match="uses 2 sensors"):
        load_policy(b, expect_sensors=1)
    # a different action set (the wheel-speed pairs are in the encoder section)
    off = HEADER.size + 4 + 2 + 2  # head, 2 sensors, 1 edge
    tampered = bytearray(b)
    struct.pack_into("<hh", tampered, off, 500, 500)
    with pytest.raises(PolicyError, match="action set"):
        load_policy(fix_crc(tampered))


def test_goal_outside_grid_and_bad_metadata_are_rejected():
    b = bytearray(cell_file())
    struct.pack_into("<HH", b, HEADER.size + 8, 10, 0)
    with pytest.raises(PolicyError, match=r"goal \(10,0\)"):
        load_policy(fix_crc(b))
    enc_len, meta_len = struct.unpack_from("<II", b, 40)
    start = HEADER.size + enc_len
    for bad, why in ((b"[" * meta_len, "not UTF-8 JSON"), (b"\xff" * meta_len, "not UTF-8 JSON"),
                     (b"[1]".ljust(meta_len), "not a JSON object")):
        c = bytearray(cell_file())
        c[start:start + meta_len] = bad
        with pytest.raises(PolicyError, match=why):
            load_policy(fix_crc(c))


def test_deeply_nested_metadata_of_max_size_is_a_policy_error():
    enc = CellEncoder(1, 1, 1)
    b = bytearray(dump_policy(enc, [0, 0, 0, 0], "int8", 1.0, goals=[(0, 0)]))
    fields = list(HEADER.unpack_from(b, 0))
    fields[13] = MAX_METADATA_BYTES
    enc_sec = bytes(b[HEADER.size:HEADER.size + fields[12]])
    body = HEADER.pack(*fields) + enc_sec + b"[" * MAX_METADATA_BYTES + bytes(4)
    with pytest.raises(PolicyError, match="metadata"):
        load_policy(fix_crc(body + bytes(4)))


def test_files_on_disk(tmp_path):
    good = tmp_path / "p.qtab"
    good.write_bytes(cell_file())
    assert load_policy(good).n_states == 400
    assert load_policy(str(good)).n_states == 400
    with pytest.raises(PolicyError, match="cannot read"):
        load_policy(tmp_path / "missing.qtab")
    with pytest.raises(PolicyError, match="cannot read"):
        load_policy(tmp_path)
    huge = tmp_path / "huge.qtab"
    with open(huge, "wb") as f:  # sparse: costs no disk, must not be read
        f.truncate(MAX_FILE_BYTES + 1)
    with pytest.raises(PolicyError, match="limit"):
        load_policy(huge)


def test_writer_refuses_inconsistent_input():
    enc = CellEncoder(2, 2, 1)
    with pytest.raises(ValueError):
        dump_policy(enc, [0] * 15, "int8", 1.0, goals=[(0, 0)])
    with pytest.raises(ValueError):
        dump_policy(enc, [-128] + [0] * 15, "int8", 1.0, goals=[(0, 0)])
    with pytest.raises(OverflowError):
        dump_policy(enc, [128] + [0] * 15, "int8", 1.0, goals=[(0, 0)])
    with pytest.raises(ValueError):
        dump_policy(enc, [0] * 16, "int8", 1.0, goals=[])
    with pytest.raises(ValueError):
        dump_policy(enc, [0] * 16, "int4", 1.0, goals=[(0, 0)])
    with pytest.raises(ValueError):
        dump_policy(enc, [0] * 16, "int8", 0.0, goals=[(0, 0)])
    with pytest.raises(ValueError, match="control period"):
        dump_policy(enc, [0] * 16, "int8", 1.0, goals=[(0, 0)], control_period_us=0)
    with pytest.raises(ValueError, match="differs from the cell policy's grid"):
        dump_policy(enc, [0] * 16, "int8", 1.0, goals=[(0, 0)], map_geometry=MapGeometry(500, 3, 2))
    sec = SectorEncoder(4, (0,), (500,))
    with pytest.raises(ValueError, match="training map's geometry"):
        dump_policy(sec, [0] * sec.n_states * 4, "int8", 1.0)
    with pytest.raises(ValueError, match="1..65535"):
        dump_policy(sec, [0] * sec.n_states * 4, "int8", 1.0, map_geometry=MapGeometry(500, 0, 10))


def test_free_form_fields_at_extremes_are_accepted_and_printable():
    for pid, created in ((0, 0), (2**32 - 1, 2**63 - 1)):
        p = load_policy(set_field(set_field(cell_file(), 9, pid), 10, created))
        h = p.header()
        assert (p.policy_id, p.created) == (pid, created)
        assert h["policy_id"] == f"0x{pid:08x}" and h["created_utc"][:4] in ("1970", "9999")


def test_version_1_files_are_refused_and_upgrade_to_the_same_bytes():
    for b in (cell_file(), dump_policy(SectorEncoder(), [1] * SectorEncoder().n_states * 4, "int8", 0.5,
                                       metadata={"map": "paper10"}, map_geometry=PAPER10, created=9)):
        old = as_version_1(b)
        with pytest.raises(PolicyError, match="^format version 1.0 records no control period") as err:
            load_policy(old)
        assert "\n" not in str(err.value) and "qnav policy upgrade" in str(err.value)
        geometry = None if b[12] == 1 else PAPER10  # a cell policy's geometry is its grid
        new = upgrade_policy(old, robot_spec.CONTROL_PERIOD_US, geometry)
        assert new == b  # header grows, everything after it is copied: same table, id, time
        assert old[HEADER_V1.size:-4] == new[HEADER.size:-4]


def test_upgrade_refuses_what_it_cannot_know_or_trust():
    old_cell = as_version_1(cell_file())
    with pytest.raises(PolicyError, match="differs from the cell policy's grid"):
        upgrade_policy(old_cell, 50_000, MapGeometry(500, 12, 10))
    with pytest.raises(PolicyError, match="control period 0 us"):
        upgrade_policy(old_cell, 0)
    damaged = bytearray(old_cell)
    damaged[70] ^= 1
    with pytest.raises(PolicyError, match="CRC32 mismatch"):
        upgrade_policy(bytes(damaged), 50_000)
    with pytest.raises(PolicyError, match="nothing to upgrade"):
        upgrade_policy(cell_file(), 50_000)
    enc = SectorEncoder()
    old_sector = as_version_1(dump_policy(enc, [0] * enc.n_states * 4, "int8", 1.0, map_geometry=PAPER10))
    with pytest.raises(PolicyError, match="name the map"):
        upgrade_policy(old_sector, 50_000)
    assert load_policy(upgrade_policy(old_sector, 40_000, MapGeometry(250, 20, 8))).map_geometry == (250, 20, 8)


@pytest.mark.parametrize("code, name", [(3, "sector-memory-tick"), (5, "sector-unmapped")])
def test_a_removed_experiment_kind_is_refused_by_name(code, name):
    """A file of a policy kind that was an experiment and left qnav (docs/research.md): its
    header alone, with a valid CRC, gets one line naming the kind and where it still runs."""
    head = HEADER.pack(MAGIC, 2, 0, HEADER.size, 0, code, 1, 4, 405, 0x1234, 1_700_000_000, 0.5, 0, 0,
                       robot_spec.CONTROL_PERIOD_US, 500, 10, 10)
    want = f"policy kind {name} was an experiment, removed from qnav; git checkout e026a1b to run it"
    with pytest.raises(PolicyError) as err:
        load_policy(head + CRC.pack(zlib.crc32(head)))
    assert str(err.value) == want
    with pytest.raises(PolicyError) as err:  # a version 1 file of it is not upgraded either
        upgrade_policy(as_version_1(head + CRC.pack(zlib.crc32(head))), robot_spec.CONTROL_PERIOD_US, PAPER10)
    assert str(err.value) == want


def test_config_mismatch_names_both_values():
    cell = load_policy(cell_file(control_period_us=50_000))
    assert config_mismatch(cell, 50_000, 500) == ""
    assert config_mismatch(cell, 40_000, 500) == "policy control period 50000 us != robot 40000 us"
    assert config_mismatch(cell, 50_000, 250) == "policy cell size 500 mm != robot 250 mm"
    enc = SectorEncoder()
    sector = load_policy(dump_policy(enc, [0] * enc.n_states * 4, "int8", 1.0, map_geometry=PAPER10))
    assert config_mismatch(sector, 50_000, 250) == ""  # sector policies do not observe cells
    assert config_mismatch(sector, 25_000, 500) == "policy control period 50000 us != robot 25000 us"
