"""Training kinds: what the ground station knows of each policy kind, and the one
registry of them (the station's half of `firmware_py.kinds`, keyed by the same name).

A `TrainingKind` holds what training, evaluating and exporting a kind needs: its
hyperparameters (a dataclass, nested in `TrainConfig.options`), recipe, learners,
trainer and greedy evaluation (as "module:function" references imported when used,
so the `qnav` parser and the config never import numba), and how its encoder is
rebuilt from a run's meta.json. `qnav train`, `eval`, `export`, `sweep` and `study`
reach a kind only through `of_name` and `names`; a new kind is a package with a
`KIND` passed to `register`. Option names: `ground_station.learn.config`.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import Field, dataclass, field, fields
from typing import Any

__all__ = ["TrainingKind", "option", "register", "unregister", "of_name", "names", "resolve", "flat_names",
           "shipped_recipes", "DEFAULT", "SHIPPED"]


def option(default: Any, help: str, *, flag: str | None = None) -> Any:
    """A hyperparameter field: its help text is its `qnav train --help` line; `flag` (a flat
    name) when it is not the kind's prefix + the field's name."""
    meta = {"help": help} if flag is None else {"help": help, "flag": flag}
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class TrainingKind:
    """One policy kind as the station trains it. `train(cfg, gridmap, progress) -> TrainResult` and
    `evaluate(q, run: TrainingRun, gridmap, *, sample, seed, full) -> dict` (`full`: with the
    baselines `qnav eval` prints) are "module:function" references or callables; `validate(cfg)`
    raises ValueError (one line) on options that cannot train."""

    name: str  # the firmware_py.kinds name (the .qtab kind)
    summary: str  # one line for --help
    options: type  # dataclass of the kind's own hyperparameters (defaults = its options' defaults)
    prefix: str  # flat-name prefix of its options ("sector_" -> --sector-guidance)
    train: str | Callable[..., Any]
    evaluate: str | Callable[..., Any]
    encoder_from_dict: Callable[[dict], Any]  # meta.json "encoder" -> the robot's encoder
    learners: tuple[str, ...] = ("q",)  # the learners its trainer implements (config.LEARNERS order)
    recipe: Mapping[str, Any] = field(default_factory=dict)  # flat name -> value, over the defaults
    validate: Callable[[Any], None] | None = None
    plot: str | Callable[..., Any] | None = None  # (q, run, gridmap) -> PNG bytes (`qnav eval --plot`)
    sweep_sample: int | None = None  # episodes a sweep's evaluation samples (None: every one)

    def flat_name(self, f: Field) -> str:
        return str(f.metadata.get("flag") or self.prefix + f.name)

    def option_fields(self) -> list[tuple[str, Field]]:
        """(flat name, field) of each of the kind's options."""
        return [(self.flat_name(f), f) for f in fields(self.options)]


# the shipped kinds' packages, each with a `KIND` (imported on first use)
SHIPPED = ("ground_station.learn.cell", "ground_station.learn.sector", "ground_station.learn.sector_memory")
DEFAULT = "cell"  # what `qnav train` trains unless told: the paper's state
_BY_NAME: dict[str, TrainingKind] = {}
_SHIPPED_LOADED = False


def _shipped() -> dict[str, TrainingKind]:
    """The registry, with the shipped kinds in it. Loaded on first use, not at import: each
    shipped package imports this module for `TrainingKind`, and may be imported first."""
    global _SHIPPED_LOADED
    if not _SHIPPED_LOADED:
        _SHIPPED_LOADED = True
        for module in SHIPPED:
            kind = importlib.import_module(module).KIND
            _BY_NAME.setdefault(kind.name, kind)
    return _BY_NAME


def register(kind: TrainingKind) -> TrainingKind:
    """Make `kind` trainable (`qnav train --encoding NAME` and the rest); returns it."""
    _shipped()
    other = _BY_NAME.get(kind.name)
    if other is not None and other is not kind:
        raise ValueError(f"training kind {kind.name!r} is registered already")
    _BY_NAME[kind.name] = kind
    return kind


def unregister(name: str) -> None:
    _BY_NAME.pop(name, None)


def of_name(name: str) -> TrainingKind:
    """The kind called `name`; ValueError naming the known ones if there is none."""
    try:
        return _shipped()[name]
    except KeyError:
        raise ValueError(f"encoding must be one of {', '.join(names())}, got {name!r}") from None


def shipped_recipes() -> dict[str, str]:
    """`qnav train --recipe` names: shipped-<kind> -> kind, for the kinds policies/ ships."""
    return {f"shipped-{kind}": kind for kind in names()[:len(SHIPPED)]}


def names() -> list[str]:
    """Registered kinds, the shipped ones first in their order."""
    return list(_shipped())


def resolve(ref: str | Callable[..., Any]) -> Callable[..., Any]:
    """A "module:function" reference imported now (or a callable as it is)."""
    if callable(ref):
        return ref
    module, _, attr = ref.partition(":")
    return getattr(importlib.import_module(module), attr)  # type: ignore[no-any-return]


def flat_names() -> dict[str, list[str]]:
    """Every kind option's flat name -> the kinds that read it."""
    out: dict[str, list[str]] = {}
    for kind in _shipped().values():
        for flat, _ in kind.option_fields():
            out.setdefault(flat, []).append(kind.name)
    return out

