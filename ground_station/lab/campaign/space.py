"""Search spaces over `TrainConfig` fields, expanded into a seeded job list.

`--space FIELD=grid:a,b,c` adds a grid axis; `FIELD=uniform:lo,hi`,
`FIELD=loguniform:lo,hi`, `FIELD=int:lo,hi` and `FIELD=choice:a,b,c` are
sampled `--samples` times from the campaign seed. The expansion happens
here, once, on the driver: every engine (the local pool, Ray tasks, Ray
Tune) receives the same explicit list of configs, so the same seeded
campaign gives the same result file whatever runs it.
"""

from __future__ import annotations

import itertools
import math
import random
from dataclasses import dataclass, fields
from typing import Any

from ground_station.learn.config import TrainConfig

KINDS = ("grid", "uniform", "loguniform", "int", "choice")


@dataclass(frozen=True)
class Axis:
    field: str
    kind: str
    values: tuple[Any, ...]  # grid/choice: the values; uniform/loguniform/int: (lo, hi)


def _field_types() -> dict[str, Any]:
    """Flat name -> type of every training option (common fields and every kind's)."""
    from ground_station.learn import kinds

    out = {f.name: f.type for f in fields(TrainConfig) if f.name != "options"}
    for name in kinds.names():
        out.update({flat: f.type for flat, f in kinds.of_name(name).option_fields()})
    return out


def _convert(name: str, text: str) -> Any:
    typ = str(_field_types()[name])
    text = text.strip()
    try:
        if "bool" in typ:
            if text.lower() in ("1", "true", "yes"):
                return True
            if text.lower() in ("0", "false", "no"):
                return False
            raise ValueError
        if "int" in typ and "float" not in typ:
            return int(float(text)) if float(text).is_integer() else int(text)
        if "float" in typ:
            v = float(text)
            if not math.isfinite(v):
                raise ValueError
            return v
    except ValueError:
        raise ValueError(f"--space {name}: {text!r} is not a valid {typ.replace('typing.', '')}") from None
    return text


def parse_axis(spec: str) -> Axis:
    """`FIELD=KIND:VALUES` -> Axis, with a one-line error naming what is wrong."""
    name, sep, rest = spec.partition("=")
    name = name.strip().replace("-", "_")
    kind, sep2, values = rest.partition(":")
    if not sep or not sep2:
        raise ValueError(f"bad --space {spec!r}: use FIELD=KIND:VALUES, KIND one of {', '.join(KINDS)}")
    if name not in _field_types():
        raise ValueError(f"--space {spec!r}: TrainConfig has no field {name!r}")
    if name == "seed":
        raise ValueError("--space seed: seeds come from --seeds (and the campaign's --seed)")
    kind = kind.strip()
    parts = [v for v in values.split(",") if v.strip()]
    if kind in ("grid", "choice"):
        if not parts:
            raise ValueError(f"--space {spec!r}: no values")
        return Axis(name, kind, tuple(_convert(name, v) for v in parts))
    if kind in ("uniform", "loguniform", "int"):
        if len(parts) != 2:
            raise ValueError(f"--space {spec!r}: {kind} needs LO,HI")
        lo, hi = (float(_convert(name, v)) for v in parts)
        if not lo < hi or (kind == "loguniform" and lo <= 0):
            raise ValueError(f"--space {spec!r}: need 0 < LO < HI for loguniform, LO < HI otherwise")
        return Axis(name, kind, (lo, hi))
    raise ValueError(f"--space {spec!r}: unknown kind {kind!r}, use one of {', '.join(KINDS)}")


def _sample(axis: Axis, rng: random.Random) -> Any:
    if axis.kind == "choice":
        return rng.choice(axis.values)
    lo, hi = axis.values
    if axis.kind == "uniform":
        return round(rng.uniform(lo, hi), 6)
    if axis.kind == "loguniform":
        return round(math.exp(rng.uniform(math.log(lo), math.log(hi))), 6)
    return rng.randint(int(lo), int(hi))


def points(axes: list[Axis], samples: int = 1, seed: int = 0) -> list[dict[str, Any]]:
    """The search points: the grid product, times `samples` random draws of the
    sampled axes (seeded). No axes -> one empty point."""
    names = [a.field for a in axes]
    if len(set(names)) != len(names):
        raise ValueError(f"--space names a field twice: {', '.join(names)}")
    grid = [a for a in axes if a.kind == "grid"]
    sampled = [a for a in axes if a.kind != "grid"]
    if samples < 1:
        raise ValueError(f"--samples must be >= 1, got {samples}")
    rng = random.Random(seed)
    draws = [{a.field: _sample(a, rng) for a in sampled} for _ in range(samples if sampled else 1)]
    out = []
    for combo in itertools.product(*(a.values for a in grid)):
        base = dict(zip((a.field for a in grid), combo, strict=True))
        for d in draws:
            out.append({**base, **d})
    return out


def label(point: dict[str, Any]) -> str:
    return ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in point.items()) or "base"
