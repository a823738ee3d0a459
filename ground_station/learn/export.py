"""Float Q-table -> int `.qtab` policy: symmetric quantisation, the float-vs-int
comparison and the file's metadata. The byte layout belongs to `firmware_py.policy`;
whether the int table still drives as well is judged by rollouts, because rounding
creates argmax ties that rarely change path optimality.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from array import array
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_py import kinds as robot_kinds
from firmware_py import policy as fmt
from firmware_py import robot_spec
from firmware_py.needs import DEFAULT as DEFAULT_TRAINED
from firmware_py.needs import NEEDS_KEY, TrainedFor, policy_needs

NP_DTYPES = {"int8": np.int8, "int16": np.int16}


@dataclass(frozen=True)
class Quantised:
    """An int table and the scale(s) that map it back: q ~= table * scale."""

    table: np.ndarray  # (n_states, n_actions), int8 or int16
    dtype: str
    scale: float  # the table's scale (with per-state scales: their maximum)
    state_scales: np.ndarray | None  # float32 (n_states,) or None
    rounding_ties: int  # values exactly halfway between two ints before rounding
    argmax_fixes: int = 0  # rows whose rounding tied a unique float argmax, untied (preserve_argmax)


def quantise(q: np.ndarray, dtype: str = "int8", per_state: bool = False,
             preserve_argmax: bool = False) -> Quantised:
    """Symmetric quantisation: scale = max|q| / qmax, ints = round(q / scale), half-to-even (exact
    halves counted). `per_state=True` gives each row its own float32 scale, which keeps
    small-valued rows from collapsing to ties. `preserve_argmax=True`: where a row's float argmax
    is unique but rounding tied it (rounding is monotonic, so it can only tie, never reorder), the
    tied competitors go 1 LSB below it (`untie_argmax`): the robot's greedy choice (ties to the
    lowest index) is then the float table's in every row whose float argmax is unique."""
    if dtype not in NP_DTYPES:
        raise ValueError(f"dtype must be int8 or int16, not {dtype!r}")
    q = np.asarray(q, dtype=np.float64)
    if q.ndim != 2 or q.size == 0:
        raise ValueError(f"Q-table must be a non-empty 2-D array, got shape {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError("Q-table has NaN or infinite values")
    qmax = fmt.DTYPES[fmt.DTYPE_CODES[dtype]][3]
    if per_state:
        peak = np.abs(q).max(axis=1)
        # float32 first, so quantising and dequantising use the stored value
        scales = np.where(peak > 0, peak / qmax, 1.0).astype(np.float32)
        scales = np.where(scales > 0, scales, np.float32(1.0)).astype(np.float32)  # underflow guard
        x = q / scales[:, None].astype(np.float64)
        scale = float(scales.max())
    else:
        peak = float(np.abs(q).max())
        scale = peak / qmax if peak > 0 else 1.0
        scales = None
        x = q / scale
    frac = np.abs(x - np.trunc(x))
    ties = int(np.count_nonzero(frac == 0.5))
    ints = np.clip(np.rint(x), -qmax, qmax).astype(NP_DTYPES[dtype])
    fixes = 0
    if preserve_argmax:
        ints, fixes = untie_argmax(q, ints, qmax)
    return Quantised(table=ints, dtype=dtype, scale=scale, state_scales=scales, rounding_ties=ties,
                     argmax_fixes=fixes)


def untie_argmax(q: np.ndarray, ints: np.ndarray, qmax: int) -> tuple[np.ndarray, int]:
    """`ints` with every row whose float argmax is unique but tied after rounding untied: the
    competitors at the best's int value go 1 LSB below it (or, the best at -qmax, the best 1 LSB
    up). The other values and the order among the competitors stay as rounded. Returns the new
    table and the number of rows changed."""
    out = ints.astype(np.int64)
    fixes = 0
    for s, row in enumerate(q):
        b = int(np.argmax(row))
        tied = out[s] >= out[s, b]
        tied[b] = False
        if np.count_nonzero(row == row[b]) > 1 or not tied.any():
            continue  # a tie in the float table stays one; or nothing to untie
        if out[s, b] > -qmax:
            out[s, tied] = out[s, b] - 1
        else:  # the best at the floor: lift it instead
            out[s, b] += 1
        fixes += 1
    return out.astype(ints.dtype), fixes


def tie_rate(table: np.ndarray) -> float:
    """Fraction of states whose best value is shared by two or more actions."""
    t = np.asarray(table)
    return float(np.mean((t == t.max(axis=1, keepdims=True)).sum(axis=1) > 1))


def compare(q: np.ndarray, qt: Quantised) -> dict:
    """How rounding changed the greedy choice (ties -> lowest index, as the robot's best_action)."""
    agree = np.argmax(q, axis=1) == np.argmax(qt.table, axis=1)
    return {
        "argmax_agreement": float(np.mean(agree)),
        "tie_rate": tie_rate(qt.table),
        "float_tie_rate": tie_rate(q),
        "rounding_ties": qt.rounding_ties,
        "argmax_fixes": qt.argmax_fixes,
    }


def encoder_from_dict(d: dict) -> fmt.AnyEncoder:
    """Rebuild a reference encoder from its `to_dict()` (as in meta.json), by its kind's."""
    from ground_station.learn import kinds

    kind = d.get("kind")
    removed = {name: code for code, name in fmt.REMOVED_KINDS.items()}
    if kind in removed:
        raise ValueError(fmt.removed_kind_reason(removed[kind]))
    if kind not in kinds.names():
        raise ValueError(f"unknown encoder kind {kind!r}")
    return kinds.of_name(str(kind)).encoder_from_dict(d)


def policy_bytes(qt: Quantised, encoder: fmt.AnyEncoder, *, goals=(),
                 cell_mm: int = robot_spec.DEFAULT_CELL_SIZE_MM, metadata: dict | None = None,
                 policy_id: int | None = None, created: int | None = None,
                 control_period_us: int = robot_spec.CONTROL_PERIOD_US,
                 map_geometry: fmt.MapGeometry | None = None, trained: TrainedFor | None = None) -> bytes:
    """`.qtab` bytes for a quantised table (`firmware_py.policy.dump_policy`); `trained`: the robot
    the table was trained for (default the built-in robot), whose needs the file records."""
    if qt.table.shape != (encoder.n_states, encoder.n_actions):
        raise ValueError(f"table shape {qt.table.shape} does not match the encoder's "
                         f"({encoder.n_states}, {encoder.n_actions})")
    typecode = fmt.DTYPES[fmt.DTYPE_CODES[qt.dtype]][1]
    flat = array(typecode)
    flat.frombytes(np.ascontiguousarray(qt.table, dtype=qt.table.dtype.newbyteorder("=")).tobytes())
    scales = None
    if qt.state_scales is not None:
        scales = array("f")
        scales.frombytes(np.ascontiguousarray(qt.state_scales, dtype=np.float32).tobytes())
    # what the policy needs of the robot it runs on (firmware_py.needs: the period, the wheel speed, the
    # sectors it reads, the body and wheel base its twin assumed); the robot checks exactly that
    need = policy_needs(robot_kinds.of_name(encoder.kind), encoder, trained or DEFAULT_TRAINED, control_period_us)
    metadata = {NEEDS_KEY: need, **(metadata or {})}
    return fmt.dump_policy(encoder, flat, qt.dtype, qt.scale, state_scales=scales, goals=goals,
                           cell_mm=cell_mm, metadata=metadata, policy_id=policy_id, created=created,
                           control_period_us=control_period_us, map_geometry=map_geometry)


# --- a training run directory -> policy file ------------------------------------

@dataclass
class TrainingRun:
    """What `qnav train` left in its output directory."""

    q: np.ndarray
    meta: dict
    encoder: fmt.AnyEncoder
    goals: list[tuple[int, int]]
    cell_mm: int


def load_run(run_dir: str | os.PathLike) -> TrainingRun:
    """Read DIR/q.npy and DIR/meta.json; ValueError with one line if unusable."""
    d = Path(run_dir)
    try:
        meta = json.loads((d / "meta.json").read_text())
        q = np.load(d / "q.npy", allow_pickle=False)
    except FileNotFoundError as exc:
        raise ValueError(f"{d} is not a training run folder: missing {Path(exc.filename).name}") from None
    except (OSError, ValueError) as exc:
        raise ValueError(f"{d}: unreadable run artifacts: {exc}") from None
    if not isinstance(meta, dict) or q.ndim != 2:
        raise ValueError(f"{d}: not a training run (meta.json an object, q.npy a 2-D table)")
    try:
        return run_of(q, meta)
    except ValueError as exc:
        raise ValueError(f"{d}/{exc}") from None


def run_of(q: np.ndarray, meta: dict) -> TrainingRun:
    """A TrainingRun of a table and its meta.json; ValueError naming the file at fault."""
    try:
        encoder = encoder_from_dict(meta["encoder"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"meta.json: bad encoder description ({exc})") from None
    if q.shape != (encoder.n_states, encoder.n_actions):
        raise ValueError(f"q.npy has shape {q.shape}, the encoder needs ({encoder.n_states}, {encoder.n_actions})")
    # a kind with goal slots in its table (cell) lists their cells in meta.json
    n_goals = getattr(encoder, "n_goals", None)
    goals = [(int(c), int(r)) for c, r in meta.get("goals", [])] if n_goals is not None else []
    if n_goals is not None and len(goals) != n_goals:
        raise ValueError(f"meta.json lists {len(goals)} goals for {n_goals} goal slots")
    cell_mm = meta.get("cell_mm")
    if cell_mm is None and "cell_size_m" in meta:
        cell_mm = round(float(meta["cell_size_m"]) * 1000)
    return TrainingRun(q=q, meta=meta, encoder=encoder, goals=goals,
                       cell_mm=int(cell_mm or robot_spec.DEFAULT_CELL_SIZE_MM))


def trained_for(run: TrainingRun) -> TrainedFor:
    """The robot a run was trained for (meta.json `robot`; a run without one: the built-in robot);
    ValueError (one line) if the record is malformed."""
    rec = run.meta.get("robot")
    return DEFAULT_TRAINED if rec is None else TrainedFor.from_dict(rec)


def control_period_us(run: TrainingRun) -> int:
    """The control period the run trained for (a run may record its own)."""
    return int(run.meta.get("control_period_us", robot_spec.CONTROL_PERIOD_US))


def map_geometry(run: TrainingRun) -> fmt.MapGeometry:
    """The training map's geometry for the file header: the one the kind fixes (a cell
    policy's own grid), else the map named in meta.json (ValueError with one line if unreadable)."""
    fixed = robot_kinds.of_name(run.encoder.kind).fixed_geometry(run.encoder, run.cell_mm)
    if fixed is not None:
        return fmt.MapGeometry(*fixed)
    return geometry_of_map(run.meta.get("map"), run.cell_mm)


def _load_map(name: str | None, cell_mm: int, what: str, unnamed: str):  # type: ignore[no-untyped-def]
    """A built-in map or map file at `cell_mm`; ValueError, one line: `unnamed`, or `what` NAME: why."""
    from ground_station.maps import MapError, load_map

    if not name:
        raise ValueError(unnamed)
    try:
        return load_map(str(name), cell_size_m=cell_mm / 1000)
    except (MapError, OSError) as exc:
        raise ValueError(f"{what} {name}: {exc}") from None


def geometry_of_map(name: str | None, cell_mm: int = robot_spec.DEFAULT_CELL_SIZE_MM) -> fmt.MapGeometry:
    """Geometry of a built-in map or map file (ValueError with one line if it cannot be read)."""
    gm = _load_map(name, cell_mm, "training map", "no training map named: cannot record its geometry")
    return fmt.MapGeometry(round(gm.cell_size_m * 1000), gm.width, gm.height)


def created_time(meta: dict) -> int:
    """Creation time: SOURCE_DATE_EPOCH (reproducible builds), else the run's own time, else now."""
    if os.environ.get("SOURCE_DATE_EPOCH", "").isdigit():
        return int(os.environ["SOURCE_DATE_EPOCH"])
    c = meta.get("created")
    if isinstance(c, int | float) and c >= 0:
        return int(c)
    if isinstance(c, str):
        from datetime import datetime
        try:
            return max(0, int(datetime.fromisoformat(c.replace("Z", "+00:00")).timestamp()))
        except ValueError:
            pass
    return int(time.time())


def file_metadata(run: TrainingRun, qt: Quantised) -> dict:
    """The training facts carried in the file (bounded: big fields dropped)."""
    keep = {k: run.meta[k] for k in ("encoding", "map", "targets", "config", "steps", "train_seconds",
                                     "created", "seed") if k in run.meta}
    keep["quantisation"] = {"dtype": qt.dtype, "per_state_scales": qt.state_scales is not None}
    if qt.argmax_fixes:
        keep["quantisation"]["argmax_fixes"] = qt.argmax_fixes
    # the robot's localiser needs the training map's cells (firmware_py.mapdata); an unnamed or
    # unreadable map: the file carries no grid and the robot runs on odometry
    with contextlib.suppress(ValueError):
        keep[META_GRID] = map_grid_rows(str(run.meta.get("map") or ""), run.cell_mm)
    if len(json.dumps(keep)) > fmt.MAX_METADATA_BYTES:
        keep.pop("config", None)
    return keep


META_GRID = "map_grid"  # firmware_py.mapdata.META_KEY
META_PLANNER = "local_planner"  # firmware_py.kinds.sector.config.META_KEY


def planner_metadata(text: str, kind: str, meta: dict) -> dict:
    """The `local_planner` metadata value from a JSON object of parameters (ValueError, one line,
    for bad JSON, a bad parameter, a policy that is not a plain sector policy or carries no map)."""
    from firmware_py.kinds.sector.config import LocalPlannerConfig

    owner = robot_kinds.METADATA_KEYS[META_PLANNER]  # the kind that reads it (its parse_metadata)
    if kind != owner:
        raise ValueError(f"--local-planner: a {kind} policy cannot steer on the local planner ({owner} only)")
    if META_GRID not in meta:
        raise ValueError("--local-planner: the policy carries no map (its training map could not be read)")
    try:
        value = json.loads(text)
    except ValueError as exc:
        raise ValueError(f"--local-planner: not JSON: {str(exc).splitlines()[0]}") from None
    return LocalPlannerConfig.from_metadata(value).to_metadata()


def map_grid_rows(name: str, cell_mm: int = robot_spec.DEFAULT_CELL_SIZE_MM) -> list[str]:
    """A map's cells as `map_grid` rows ('.' free, '@' occupied); ValueError if it cannot be read."""
    gm = _load_map(name, cell_mm, "map", "no map named")
    return ["".join("@" if v else "." for v in row) for row in gm.occ.tolist()]


def attach_map(data: bytes, map_name: str) -> bytes:
    """A `.qtab` with the named map's cells in its metadata (`map_grid`), all else unchanged;
    ValueError (one line) if the file or map is unusable or the map's size differs from the file's."""
    try:
        pol = fmt.load_policy(data)
    except fmt.PolicyError as exc:
        raise ValueError(str(exc)) from None
    geo = pol.map_geometry
    rows = map_grid_rows(map_name, geo.cell_mm)
    if (len(rows[0]), len(rows)) != (geo.width, geo.height):
        raise ValueError(f"map {map_name} is {len(rows[0])}x{len(rows)} cells, the policy was trained on "
                         f"{geo.width}x{geo.height}")
    meta = dict(pol.metadata)
    meta[META_GRID] = rows
    return with_metadata(pol, meta)


def with_metadata(pol: fmt.Policy, meta: dict) -> bytes:
    """`pol`'s file with `meta` as its metadata, everything else (table, policy id, creation time,
    geometry) unchanged."""
    geo = pol.map_geometry
    typecode = fmt.DTYPES[fmt.DTYPE_CODES[pol.dtype]][1]
    scales = array("f", pol.state_scales) if pol.state_scales is not None else None
    return fmt.dump_policy(pol.encoder, array(typecode, pol.table), pol.dtype, pol.scale, state_scales=scales,
                           goals=pol.goals, cell_mm=pol.cell_mm or geo.cell_mm, metadata=meta,
                           policy_id=pol.policy_id, created=pol.created,
                           control_period_us=pol.control_period_us, map_geometry=geo)
