"""Hostile policy files: thousands of mutated files, every one rejected with
PolicyError and nothing else, loader memory bounded by the file size.

Mutations run in memory (load from bytes). Two families:

* rejected-by-construction (10 000): truncation, extension, bit flips, byte
  overwrites with the CRC left stale; and header fields set to extremes,
  huge declared sizes, swapped encoder kinds, shifted lengths with the CRC
  recomputed, so the field checks behind the CRC are exercised too.
* CRC-recomputed random flips anywhere: such a file may be a legitimately
  different valid policy (a flipped table entry), so it is either rejected
  with PolicyError or loaded as a complete, self-consistent table.
"""

import random
import struct
import tracemalloc
import zlib

import pytest

from firmware_py.kinds.cell.encoder import CellEncoder
from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.policy import (
    CRC,
    HEADER,
    MAX_FILE_BYTES,
    MapGeometry,
    PolicyError,
    dump_policy,
    load_policy,
)

N_REJECTED = 10_000

# the extremes each header field is set to (index into HEADER's fields);
# policy id and creation time are free-form, so only invalid extremes here
EXTREMES = {
    0: [b"\x00" * 4, b"\xff" * 4, b"qtab", b"QTA\x00"],
    1: [0, 1, 3, 255],  # 1: a version 1.x file (no control period or geometry) is refused too
    3: [0, 1, 47, 48, 57, 59, 0xFFFF],
    4: [0x2, 0x80000000, 0xFFFFFFFF],
    5: [0, 3, 255],
    6: [0, 3, 255],
    7: [0, 1, 3, 5, 0xFFFF],
    8: [0, 1, 2**31, 2**32 - 1],
    10: [-1, -(2**63)],
    11: [0.0, -0.0, -1.0, float("nan"), float("inf"), float("-inf")],
    12: [0, 1, 2**31, 2**32 - 1],
    13: [2**16, 2**31, 2**32 - 1],
    14: [0],  # control period
    15: [0],  # map geometry: cell mm, width, height (any other value is a valid sector header)
    16: [0],
    17: [0],
}


def base_files() -> list[bytes]:
    rng = random.Random(0)
    out = []
    cell = CellEncoder(10, 10, 4)
    goals = [(0, 0), (9, 0), (0, 9), (9, 9)]
    for dtype, hi in (("int8", 127), ("int16", 32767)):
        t = [rng.randint(-hi, hi) for _ in range(cell.n_states * 4)]
        out.append(dump_policy(cell, t, dtype, 0.1, goals=goals, metadata={"map": "paper10", "targets": "ABCD"}))
    sec = SectorEncoder(8, (0, 1, 7), (350, 700))
    t = [rng.randint(-127, 127) for _ in range(sec.n_states * 4)]
    paper10 = MapGeometry(500, 10, 10)
    out.append(dump_policy(sec, t, "int8", 0.5, metadata={"encoding": "sector"}, map_geometry=paper10))
    out.append(dump_policy(sec, t, "int8", 0.5, state_scales=[0.5] * sec.n_states, control_period_us=40_000,
                           map_geometry=paper10))
    return out


def fix_crc(b) -> bytes:
    body = bytes(b[:-4])
    return body + CRC.pack(zlib.crc32(body))


def mutate_rejected(base: bytes, rng: random.Random) -> bytes:
    """One mutation that no loader may accept."""
    n = len(base)
    op = rng.randrange(9)
    if op == 0:  # truncation, anywhere including inside the header
        return base[:rng.randrange(n)]
    if op == 1:  # extension
        return base + rng.randbytes(rng.randint(1, 64))
    if op == 2:  # bit flips, CRC stale
        b = bytearray(base)
        for _ in range(rng.randint(1, 8)):
            i = rng.randrange(n * 8)
            b[i // 8] ^= 1 << (i % 8)
        return bytes(b)
    if op == 3:  # a run of bytes overwritten, CRC stale
        b = bytearray(base)
        i = rng.randrange(n)
        run = rng.randbytes(rng.randint(1, 16))
        b[i:i + len(run)] = run
        return bytes(b[:n]) if bytes(b[:n]) != base else bytes(b[:n - 1])
    if op in (4, 5):  # header field at an extreme, CRC recomputed
        fields = list(HEADER.unpack_from(base, 0))
        idx = rng.choice(list(EXTREMES))
        fields[idx] = rng.choice(EXTREMES[idx])
        return fix_crc(HEADER.pack(*fields) + base[HEADER.size:])
    if op == 6:  # huge or off-by-k declared sizes, CRC recomputed
        fields = list(HEADER.unpack_from(base, 0))
        idx = rng.choice([8, 12, 13])
        fields[idx] = (fields[idx] + rng.choice([-1, 1, 2**31, rng.randint(2, 2**32)])) % 2**32
        return fix_crc(HEADER.pack(*fields) + base[HEADER.size:])
    if op == 7:  # truncated or extended, then the CRC made to match
        cut = rng.randint(HEADER.size, n - 1)
        b = base[:cut] if rng.random() < 0.5 else base[:-4] + rng.randbytes(rng.randint(1, 64)) + base[-4:]
        return fix_crc(b)
    # swapped encoder kind or dtype, CRC recomputed
    fields = list(HEADER.unpack_from(base, 0))
    if rng.random() < 0.5:
        fields[5] = 3 - fields[5]
    else:
        fields[6] = 3 - fields[6]
    return fix_crc(HEADER.pack(*fields) + base[HEADER.size:])


def test_ten_thousand_mutated_files_are_all_rejected_with_policy_error():
    rng = random.Random(20240611)
    bases = base_files()
    for b in bases:
        load_policy(b)  # the seeds are valid
    reasons: dict[str, int] = {}
    for i in range(N_REJECTED):
        bad = mutate_rejected(bases[i % len(bases)], rng)
        try:
            load_policy(bad)
        except PolicyError as exc:
            msg = str(exc)
            assert msg and "\n" not in msg
            key = msg.split(" ")[0]
            reasons[key] = reasons.get(key, 0) + 1
        else:
            pytest.fail(f"mutation {i} accepted: header {HEADER.unpack_from(bad, 0) if len(bad) >= HEADER.size else bad!r}")
    # the mix reached past the CRC into the field checks, not only the CRC
    assert reasons.get("CRC32", 0) < N_REJECTED // 2
    assert len(reasons) >= 8, reasons


def test_crc_consistent_random_flips_load_whole_or_not_at_all():
    rng = random.Random(7)
    bases = base_files()
    accepted = 0
    for i in range(2000):
        base = bases[i % len(bases)]
        b = bytearray(base)
        for _ in range(rng.randint(1, 4)):
            j = rng.randrange(len(b) - 4)
            b[j] ^= 1 << rng.randrange(8)
        try:
            p = load_policy(fix_crc(b))
        except PolicyError:
            continue
        accepted += 1  # a different but complete policy (e.g. a flipped table entry)
        assert len(p.table) == p.n_states * p.n_actions == p.encoder.n_states * p.encoder.n_actions
        assert p.size == len(b)
        p.header()
        p.best_action(p.n_states - 1)
    assert 0 < accepted < 2000


def test_loader_memory_is_bounded_by_file_size():
    rng = random.Random(11)
    bases = base_files()
    tracemalloc.start()
    try:
        for i in range(600):
            base = bases[i % len(bases)]
            bad = mutate_rejected(base, rng) if i % 3 else fix_crc(
                HEADER.pack(*[*HEADER.unpack_from(base, 0)[:8], 2**32 - 1, *HEADER.unpack_from(base, 0)[9:]])
                + base[HEADER.size:])
            tracemalloc.reset_peak()
            before = tracemalloc.get_traced_memory()[0]
            with pytest.raises(PolicyError):
                load_policy(bad)
            peak = tracemalloc.get_traced_memory()[1] - before
            assert peak <= 4 * len(bad) + 64 * 1024, (i, peak, len(bad))
    finally:
        tracemalloc.stop()


def test_huge_declared_sizes_with_matching_crc_allocate_nothing_big():
    base = base_files()[0]
    fields = list(HEADER.unpack_from(base, 0))
    for idx in (8, 12, 13):
        f = list(fields)
        f[idx] = 2**32 - 1
        with pytest.raises(PolicyError):
            load_policy(fix_crc(HEADER.pack(*f) + base[HEADER.size:]))
    with pytest.raises(PolicyError, match="limit"):
        load_policy(bytes(MAX_FILE_BYTES + 1))
    assert struct.calcsize("<I") == CRC.size
