"""The `.qtab` int policy file: format constants, the robot's loader and the one byte-level writer.

This module is the single definition of the byte layout (spec, with the field table:
docs/policy-format.md). The robot loads files with `load_policy`; the ground station's exporter
quantises a float table and hands the ints to `dump_policy` so the layout is never written twice.

Pure Python, no numpy: the table lives in an `array` ('b' int8 or 'h' int16) exposed as a read-only
memoryview. The loader checks every field against the file size and the robot's configuration before
it allocates anything, and either returns a complete `Policy` or raises `PolicyError` with a
one-line reason -- never a partial table.

Version 1.x files (no control period, no geometry) are refused with the command that migrates them
(`qnav policy upgrade`, built on `upgrade_policy`). `config_mismatch` is the one rule for whether a
policy fits a robot's configuration.
"""

from __future__ import annotations

import json
import math
import os
import struct
import sys
import time
import zlib
from array import array
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

from firmware_py import kinds, robot_spec
from firmware_py.kinds.base import PAIR as _PAIR
from firmware_py.kinds.base import Encoder, PolicyKind, best_action
from firmware_py.mapdata import MapDataError, OccupancyGrid, describe, grid_from_metadata

# --- format constants ---------------------------------------------------------
MAGIC = b"QTAB"
VERSION_MAJOR = 2
VERSION_MINOR = 0

# magic, major, minor, header_size, flags, kind, dtype, n_actions, n_states, policy_id, created
# (unix s), scale, enc_len, meta_len, control_period_us, map_cell_mm, map_width, map_height
HEADER = struct.Struct("<4sBBHIBBHIIqdIIIHHH")
assert HEADER.size == 58
HEADER_V1 = struct.Struct("<4sBBHIBBHIIqdII")  # what a 1.x file starts with; read only by upgrade_policy
assert HEADER_V1.size == 48
CRC = struct.Struct("<I")

FLAG_PER_STATE_SCALES = 0x1
KNOWN_FLAGS = FLAG_PER_STATE_SCALES  # any other bit set -> reject (see the spec)

# Kind codes and names live in the registry (firmware_py.kinds); codes of experiments removed from
# qnav (docs/research.md) are never reused, and a file of one is refused by name (`removed_kind_reason`)
REMOVED_KINDS = kinds.REMOVED
REMOVED_AT = kinds.REMOVED_AT

DTYPE_INT8 = 1
DTYPE_INT16 = 2
# code -> (name, array typecode, itemsize, max magnitude of a symmetric value)
DTYPES = {DTYPE_INT8: ("int8", "b", 1, 127), DTYPE_INT16: ("int16", "h", 2, 32767)}
DTYPE_CODES = {v[0]: k for k, v in DTYPES.items()}

MAX_METADATA_BYTES = 16384
MAX_FILE_BYTES = 64 * 1024 * 1024  # far above any table the robot can hold
MIN_FILE_BYTES = HEADER.size + CRC.size

_ORDER_NATIVE = sys.byteorder == "little"


AnyEncoder = Encoder  # any registered kind's encoder (firmware_py.kinds.base.Encoder)


class PolicyError(Exception):
    """A policy file is unusable; the message is a one-line reason."""


def removed_kind_reason(kind: int) -> str:
    """The one-line refusal of a file whose kind code is in REMOVED_KINDS."""
    return (f"policy kind {REMOVED_KINDS[kind]} was an experiment, removed from qnav; "
            f"git checkout {REMOVED_AT} to run it")


class MapGeometry(NamedTuple):
    """The map a policy was trained for: cell size (mm) and grid size (cells)."""

    cell_mm: int
    width: int
    height: int

    def __str__(self) -> str:
        return f"{self.width}x{self.height} cells of {self.cell_mm} mm"


@dataclass(frozen=True)
class Policy:
    """A validated int Q-table with everything needed to use it on the robot."""

    encoder: AnyEncoder
    dtype: str
    n_states: int
    n_actions: int
    scale: float
    policy_id: int
    crc: int
    created: int
    metadata: dict[str, Any]  # the file's JSON object
    table: memoryview  # read-only, flat, n_states * n_actions ints
    state_scales: memoryview | None = None  # read-only float32 per state, or None
    goals: tuple[tuple[int, int], ...] = ()  # cell policies: goal index -> (col, row)
    cell_mm: int = 0  # cell policies: map cell size
    version: tuple[int, int] = (VERSION_MAJOR, VERSION_MINOR)
    size: int = 0  # file size in bytes
    control_period_us: int = 0  # the period the actions were trained for (load_policy sets it)
    map_geometry: MapGeometry = MapGeometry(0, 0, 0)  # the training map (load_policy sets it)
    map_grid: OccupancyGrid | None = None  # the training map's cells, if the file carries them (mapdata)
    kind_config: Any = None  # what the kind read from the metadata (`PolicyKind.parse_metadata`), or None

    @property
    def kind(self) -> str:
        return self.encoder.kind

    def row(self, state: int) -> memoryview:
        """The int Q-values of one state (a read-only memoryview slice)."""
        if not 0 <= state < self.n_states:
            raise IndexError(f"state {state} outside 0..{self.n_states - 1}")
        a = self.n_actions
        return self.table[state * a:(state + 1) * a]

    def best_action(self, state: int) -> int:
        """Greedy action; ties break to the lowest index (kinds.base.best_action)."""
        return best_action(self.row(state))

    def header(self) -> dict[str, Any]:
        """JSON-able header fields (what `qnav policy inspect` prints)."""
        d = {
            "format_version": f"{self.version[0]}.{self.version[1]}",
            "kind": self.kind,
            "encoder": self.encoder.to_dict(),
            "dtype": self.dtype,
            "n_states": self.n_states,
            "n_actions": self.n_actions,
            "scale": self.scale,
            "per_state_scales": self.state_scales is not None,
            "policy_id": f"0x{self.policy_id:08x}",
            "crc32": f"0x{self.crc:08x}",
            "created": self.created,
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(min(self.created, 253402300799))),
            "bytes": self.size,
            "control_period_us": self.control_period_us,
            "map_geometry": self.map_geometry._asdict(),
            "map_grid": self.map_grid.summary() if self.map_grid is not None else None,
            "metadata": self.metadata,
        }
        d.update(kinds.of_policy(self).header_fields(self))
        return d


# --- loading ----------------------------------------------------------------------

def _read_bounded(path: str | os.PathLike[str]) -> bytes:
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size > MAX_FILE_BYTES:
                raise PolicyError(f"file is {size} bytes, more than the {MAX_FILE_BYTES} limit")
            data = f.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise PolicyError(f"cannot read {os.fspath(path)}: {exc.strerror or exc}") from None
    if len(data) > MAX_FILE_BYTES:
        raise PolicyError(f"file is more than the {MAX_FILE_BYTES} byte limit")
    return data


def _kind(code: int) -> PolicyKind:
    """The registered kind of a file's kind code; PolicyError naming a removed or unknown one."""
    if code in REMOVED_KINDS:
        raise PolicyError(removed_kind_reason(code))
    kind = kinds.of_code(code)
    if kind is None:
        raise PolicyError(f"unknown encoder kind {code}")
    return kind


def _unpack_encoder(kind: PolicyKind, sec: bytes, n_actions: int, expect_sensors: int
                    ) -> tuple[AnyEncoder, tuple[tuple[int, int], ...], int]:
    """Encoder section -> (encoder, goals, cell_mm); every length checked exactly."""
    try:
        got = kind.unpack(sec, n_actions, expect_sensors)
    except (ValueError, struct.error) as exc:
        raise PolicyError(str(exc)) from None
    off = got.actions_at
    if len(sec) != off + _PAIR.size * n_actions:
        raise PolicyError(f"{kind.name} encoder section is {len(sec)} bytes, its fields need "
                          f"{off + _PAIR.size * n_actions}")
    actions = tuple(_PAIR.unpack_from(sec, off + _PAIR.size * i) for i in range(n_actions))
    if actions != tuple(tuple(a) for a in kind.actions):
        raise PolicyError(f"{kind.name} action set {list(actions)} differs from the robot's")
    return got.encoder, got.goals, got.cell_mm


def _declared_size(header_size: int, flags: int, dtype: int, n_actions: int, n_states: int,
                   enc_len: int, meta_len: int) -> int | None:
    """File size the header fields add up to (None if the dtype is unknown).
    Every size is a Python int, so nothing overflows; the loader demands an exact match."""
    if dtype not in DTYPES:
        return None
    scales = 4 * n_states if flags & FLAG_PER_STATE_SCALES else 0
    return header_size + enc_len + meta_len + n_states * n_actions * DTYPES[dtype][2] + scales + CRC.size


def load_policy(source: bytes | bytearray | memoryview | str | os.PathLike[str],
                expect_sensors: int = robot_spec.SENSOR_COUNT) -> Policy:
    """Validate and load a `.qtab` file (a path, or the file's bytes).

    `expect_sensors` is the robot's range-sensor count; sector policies using
    a sensor index at or above it are refused. Raises `PolicyError` only.
    """
    data = bytes(source) if isinstance(source, bytes | bytearray | memoryview) else _read_bounded(source)
    n = len(data)
    if n > MAX_FILE_BYTES:
        raise PolicyError(f"file is {n} bytes, more than the {MAX_FILE_BYTES} limit")
    if n < MIN_FILE_BYTES:
        raise PolicyError(f"file is {n} bytes, shorter than the {MIN_FILE_BYTES}-byte minimum")
    magic, major, minor = data[:4], data[4], data[5]
    if magic != MAGIC:
        raise PolicyError(f"not a .qtab file (magic {magic!r})")
    if major == 1:
        raise PolicyError(f"format version 1.{minor} records no control period or map geometry; migrate it with "
                          "`qnav policy upgrade FILE --control-period-us US [--map NAME]`")
    if major != VERSION_MAJOR:
        raise PolicyError(f"format version {major}.{minor} unsupported (this loader reads {VERSION_MAJOR}.x)")
    (_, _, _, header_size, flags, kind, dtype, n_actions, n_states, policy_id, created, scale, enc_len, meta_len,
     period_us, map_cell_mm, map_width, map_height) = HEADER.unpack_from(data, 0)
    # Check the CRC before trusting any other field: most corruption stops here.
    (stored_crc,) = CRC.unpack_from(data, n - CRC.size)
    crc = zlib.crc32(memoryview(data)[:n - CRC.size])
    if crc != stored_crc:
        declared = _declared_size(header_size, flags, dtype, n_actions, n_states, enc_len, meta_len)
        if declared is not None and declared != n:
            raise PolicyError(f"file is {n} bytes but its header declares {declared} (truncated or extended)")
        raise PolicyError(f"CRC32 mismatch (file says 0x{stored_crc:08x}, contents give 0x{crc:08x})")
    if header_size < HEADER.size:
        raise PolicyError(f"header_size {header_size} below the {HEADER.size}-byte v{VERSION_MAJOR} header")
    if flags & ~KNOWN_FLAGS:
        raise PolicyError(f"unknown flag bits 0x{flags & ~KNOWN_FLAGS:x}")
    kind_ = _kind(kind)
    if dtype not in DTYPES:
        raise PolicyError(f"unknown dtype code {dtype}")
    dname, typecode, itemsize, _ = DTYPES[dtype]
    want_actions = len(kind_.actions)
    if n_actions != want_actions:
        raise PolicyError(f"{n_actions} actions, the robot's {kind_.name} action set has {want_actions}")
    if n_states < 1:
        raise PolicyError("table has no states")
    if meta_len > MAX_METADATA_BYTES:
        raise PolicyError(f"metadata is {meta_len} bytes, more than the {MAX_METADATA_BYTES} limit")
    if not (math.isfinite(scale) and scale > 0):
        raise PolicyError(f"scale {scale!r} is not a positive finite number")
    if created < 0:
        raise PolicyError(f"creation time {created} is negative")
    if period_us < 1:
        raise PolicyError("control period is 0 us")
    geometry = MapGeometry(map_cell_mm, map_width, map_height)
    if min(geometry) < 1:
        raise PolicyError(f"map geometry {geometry} has a zero field")
    table_bytes = n_states * n_actions * itemsize
    scales_bytes = 4 * n_states if flags & FLAG_PER_STATE_SCALES else 0
    expect = _declared_size(header_size, flags, dtype, n_actions, n_states, enc_len, meta_len)
    if expect != n:
        raise PolicyError(f"fields declare {expect} bytes but the file has {n}")

    off = header_size
    enc, goals, cell_mm = _unpack_encoder(kind_, data[off:off + enc_len], n_actions, expect_sensors)
    if enc.n_states != n_states:
        raise PolicyError(f"encoder has {enc.n_states} states, table has {n_states}")
    fixed = kind_.fixed_geometry(enc, cell_mm)
    if fixed is not None and geometry != fixed:
        raise PolicyError(f"header map geometry {geometry} differs from the {kind_.name} encoder's "
                          f"{MapGeometry(*fixed)}")
    off += enc_len

    try:
        metadata = json.loads(data[off:off + meta_len].decode("utf-8")) if meta_len else {}
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise PolicyError(f"metadata is not UTF-8 JSON: {str(exc).splitlines()[0][:80]}") from None
    if not isinstance(metadata, dict):
        raise PolicyError("metadata is not a JSON object")
    off += meta_len
    try:
        grid = grid_from_metadata(metadata, *geometry)
    except MapDataError as exc:
        raise PolicyError(str(exc)) from None

    table = array(typecode)
    table.frombytes(data[off:off + table_bytes])
    if not _ORDER_NATIVE:
        table.byteswap()
    off += table_bytes
    state_scales = None
    if scales_bytes:
        arr = array("f")
        arr.frombytes(data[off:off + scales_bytes])
        if not _ORDER_NATIVE:
            arr.byteswap()
        for s in arr:
            if not (math.isfinite(s) and s > 0):
                raise PolicyError(f"state scale {s!r} is not a positive finite number")
        state_scales = memoryview(arr).toreadonly()
    policy = Policy(encoder=enc, dtype=dname, n_states=n_states, n_actions=n_actions, scale=scale,
                    policy_id=policy_id, crc=stored_crc, created=created, metadata=metadata,
                    table=memoryview(table).toreadonly(), state_scales=state_scales, goals=goals,
                    cell_mm=cell_mm, version=(major, minor), size=n, control_period_us=period_us,
                    map_geometry=geometry, map_grid=grid)
    for key, owner in kinds.METADATA_KEYS.items():
        if key in metadata and owner != kind_.name:
            raise PolicyError(f"{key} is {owner} policy metadata, not for a {kind_.name} policy")
    try:
        kind_config = kind_.parse_metadata(policy)
    except ValueError as exc:
        raise PolicyError(str(exc)) from None
    return policy if kind_config is None else replace(policy, kind_config=kind_config)


def config_mismatch(policy: Policy, control_period_us: int, cell_size_mm: int, robot_map: Any = None,
                    profile: Any = None) -> str:
    """Why `policy` must not run on this robot ('' if it may), naming both values: the control period
    and the cell size (docs/policy-format.md, "What the robot checks against its configuration"), a
    map-specific policy for another map than the robot's own (`robot_map`), and the policy's needs
    of `profile` (a RobotProfile; None: the built-in robot; firmware_py.needs)."""
    if policy.control_period_us != control_period_us:
        return f"policy control period {policy.control_period_us} us != robot {control_period_us} us"
    cell_mm = kinds.of_policy(policy).robot_cell_mm(policy)
    if cell_mm is not None and cell_mm != cell_size_mm:
        return f"policy cell size {cell_mm} mm != robot {cell_size_mm} mm"
    from firmware_py.needs import needs_mismatch, needs_of

    why = needs_mismatch(needs_of(policy), profile)
    if why:
        return why
    if (robot_map is not None and policy.map_grid is not None and kinds.of_policy(policy).map_specific
            and policy.map_grid != robot_map):  # OccupancyGrid is a dataclass: == compares the cells
        name = policy.metadata.get("map") if isinstance(policy.metadata, dict) else None
        return (f"policy map {name or ''} ({describe(policy.map_grid)}) is not the robot's map "
                f"({describe(robot_map)})").replace("map  (", "map (")
    return ""


def on_robot_map(policy: Policy, robot_map: Any) -> Policy:
    """`policy` as it runs on a robot with its own map: a kind that is not map-specific localises and
    plans on the robot's map instead of the file's training map; a map-specific one is unchanged."""
    if robot_map is None or kinds.of_policy(policy).map_specific or policy.map_grid is None:
        return policy
    return replace(policy, map_grid=robot_map,
                   map_geometry=MapGeometry(robot_map.cell_mm, robot_map.width, robot_map.height))


# --- writing ------------------------------------------------------------------------

def content_id(encoder_section: bytes, table: bytes, scales: bytes = b"") -> int:
    """Default policy id: CRC32 of what decides behaviour (encoder + table), so
    the same policy exported twice gets the same id whatever its metadata."""
    return zlib.crc32(scales, zlib.crc32(table, zlib.crc32(encoder_section)))


def _pack_encoder(encoder: AnyEncoder, goals: Sequence[tuple[int, int]],
                  cell_mm: int) -> bytes:
    kind = kinds.of_name(encoder.kind)
    return kind.pack(encoder, tuple(goals), cell_mm) + b"".join(_PAIR.pack(*a) for a in kind.actions)


def dump_policy(encoder: AnyEncoder, table: array[int], dtype: str, scale: float, *,
                state_scales: array[float] | None = None, goals: Sequence[tuple[int, int]] = (),
                cell_mm: int = robot_spec.DEFAULT_CELL_SIZE_MM, metadata: dict[str, Any] | None = None,
                policy_id: int | None = None, created: int | None = None,
                control_period_us: int = robot_spec.CONTROL_PERIOD_US,
                map_geometry: MapGeometry | None = None) -> bytes:
    """Serialise an int table (flat `array`, row-major by state) to `.qtab` bytes.

    `policy_id` defaults to `content_id(...)`; `created` to now (unix s).
    `map_geometry`: a cell policy's is its grid (derived when omitted, must
    agree when given); a sector policy must name it. ValueError on bad arguments.
    """
    code = DTYPE_CODES.get(dtype)
    if code is None:
        raise ValueError(f"dtype must be one of {sorted(DTYPE_CODES)}")
    _, typecode, _, qmax = DTYPES[code]
    n_states, n_actions = encoder.n_states, encoder.n_actions
    if len(table) != n_states * n_actions:
        raise ValueError(f"table has {len(table)} values, encoder needs {n_states}x{n_actions}")
    t = array(typecode, table)  # raises OverflowError if a value does not fit
    if any(v < -qmax for v in t):
        raise ValueError(f"symmetric {dtype} values must be >= {-qmax}")
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError("scale must be positive and finite")
    if not 1 <= control_period_us <= 0xFFFFFFFF:
        raise ValueError(f"control period {control_period_us} us outside 1..{0xFFFFFFFF}")
    geometry = _geometry_for(encoder, cell_mm, map_geometry)
    flags = 0
    sbytes = b""
    if state_scales is not None:
        s = array("f", state_scales)
        if len(s) != n_states or not all(math.isfinite(x) and x > 0 for x in s):
            raise ValueError("state_scales needs one positive finite value per state")
        if not _ORDER_NATIVE:
            s.byteswap()
        sbytes = s.tobytes()
        flags |= FLAG_PER_STATE_SCALES
    if not _ORDER_NATIVE:
        t.byteswap()
    tbytes = t.tobytes()
    enc = _pack_encoder(encoder, goals, cell_mm)
    meta = json.dumps(metadata or {}, sort_keys=True, separators=(",", ":")).encode("utf-8")
    if len(meta) > MAX_METADATA_BYTES:
        raise ValueError(f"metadata JSON is {len(meta)} bytes, limit {MAX_METADATA_BYTES}")
    pid = content_id(enc, tbytes, sbytes) if policy_id is None else policy_id
    when = int(time.time()) if created is None else int(created)
    head = HEADER.pack(MAGIC, VERSION_MAJOR, VERSION_MINOR, HEADER.size, flags, kinds.of_name(encoder.kind).code,
                       code, n_actions, n_states, pid & 0xFFFFFFFF, when, float(scale), len(enc), len(meta),
                       control_period_us, *geometry)
    body = head + enc + meta + tbytes + sbytes
    return body + CRC.pack(zlib.crc32(body))


def _geometry_for(encoder: AnyEncoder, cell_mm: int, given: MapGeometry | None) -> MapGeometry:
    """The header's map geometry: a cell policy's grid, a sector policy's training map."""
    fixed = kinds.of_name(encoder.kind).fixed_geometry(encoder, cell_mm)
    if fixed is not None:
        grid = MapGeometry(*fixed)
        if given is not None and MapGeometry(*given) != grid:
            raise ValueError(f"map geometry {MapGeometry(*given)} differs from the cell policy's grid {grid}")
        return grid
    if given is None:
        raise ValueError("a sector policy records its training map's geometry: name the map (map_geometry)")
    geometry = MapGeometry(*(int(v) for v in given))
    if not all(1 <= v <= 0xFFFF for v in geometry):
        raise ValueError(f"map geometry {geometry}: every field must be 1..65535")
    return geometry


def upgrade_policy(data: bytes, control_period_us: int, map_geometry: MapGeometry | None = None) -> bytes:
    """A version 1.x file rewritten as the current version with the control period and map
    geometry it was trained for (geometry as in `dump_policy`).

    Everything after the old header is copied byte for byte, so the policy id, creation time and
    table stay; only the header and the CRC change. Raises PolicyError with a one-line reason.
    """
    n = len(data)
    if n < HEADER_V1.size + CRC.size or data[:4] != MAGIC:
        raise PolicyError("not a .qtab file")
    (_, major, minor, header_size, flags, kind, dtype, n_actions, n_states, policy_id, created, scale,
     enc_len, meta_len) = HEADER_V1.unpack_from(data, 0)
    if major != 1:
        raise PolicyError(f"format version {major}.{minor} is not 1.x: nothing to upgrade")
    (stored_crc,) = CRC.unpack_from(data, n - CRC.size)
    if zlib.crc32(memoryview(data)[:n - CRC.size]) != stored_crc:
        raise PolicyError("CRC32 mismatch: the file is damaged, re-export it instead")
    kind_ = _kind(kind)
    if header_size < HEADER_V1.size or header_size + enc_len > n - CRC.size:
        raise PolicyError("version 1 header fields are inconsistent with the file")
    enc, _, cell_mm = _unpack_encoder(kind_, data[header_size:header_size + enc_len], n_actions,
                                      robot_spec.SENSOR_COUNT)
    try:
        geometry = _geometry_for(enc, cell_mm, map_geometry)
    except ValueError as e:
        raise PolicyError(str(e)) from None
    if not 1 <= control_period_us <= 0xFFFFFFFF:
        raise PolicyError(f"control period {control_period_us} us outside 1..{0xFFFFFFFF}")
    head = HEADER.pack(MAGIC, VERSION_MAJOR, VERSION_MINOR, HEADER.size, flags, kind, dtype, n_actions, n_states,
                       policy_id, created, scale, enc_len, meta_len, control_period_us, *geometry)
    body = head + data[header_size:n - CRC.size]
    out = body + CRC.pack(zlib.crc32(body))
    load_policy(out)  # the robot's loader judges the result
    return out
