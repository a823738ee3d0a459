"""Policy kinds: one package per kind of `.qtab` policy the robot runs, and the one
registry that maps a kind's name and file code to it (as python-can maps an
interface name to its bus class: a table of names and modules, each imported
when first asked for).

The loader (`firmware_py.policy`), the writer and the controller find a kind only
through `of_code`, `of_name` and `of_policy`, which import a shipped kind's
package (`SHIPPED`) the first time a policy of it is loaded or written: a robot
running a cell policy never imports the sector planner or the Bug memory. A new
kind is a module with a `PolicyKind` passed to `register` (or a line in `SHIPPED`).

Kind codes of experiments removed from qnav (docs/research.md; commit e026a1b has them) are reserved in
`REMOVED`: never reused, and a file of one is refused by name.
"""

from __future__ import annotations

import importlib
import threading

from firmware_py.kinds.base import Decision, DriveTick, KindDriver, Policy, PolicyKind, Unpacked

__all__ = ["Decision", "DriveTick", "KindDriver", "PolicyKind", "Unpacked", "REMOVED", "REMOVED_AT", "SHIPPED",
           "METADATA_KEYS", "register", "of_code", "of_name", "of_policy", "names"]

REMOVED = {3: "sector-memory-tick", 5: "sector-unmapped"}
REMOVED_AT = "e026a1b"  # the last commit that has them (docs/research.md)

# name -> (file code, the package whose KIND it is): imported on first use
SHIPPED: dict[str, tuple[int, str]] = {
    "cell": (1, "firmware_py.kinds.cell"),
    "sector": (2, "firmware_py.kinds.sector"),
    "sector-memory": (4, "firmware_py.kinds.sector_memory"),
}

# metadata keys a shipped kind reads (its PolicyKind.parse_metadata) -> that kind: the loader refuses a
# file of another kind that carries one (it would be ignored), without importing the owner
METADATA_KEYS: dict[str, str] = {"local_planner": "sector", "recovery_table": "sector"}

_BY_NAME: dict[str, PolicyKind] = {}
_BY_CODE: dict[int, PolicyKind] = {}
_LOADING = threading.RLock()  # the activation worker and the CLI may ask at once


def register(kind: PolicyKind) -> PolicyKind:
    """Make `kind` known to the loader, the writer and the controller; returns it."""
    if kind.code in REMOVED:
        raise ValueError(f"kind code {kind.code} belonged to {REMOVED[kind.code]} and is not reused")
    for other in (_BY_NAME.get(kind.name), _BY_CODE.get(kind.code)):
        if other is not None and other is not kind:
            raise ValueError(f"kind {kind.name!r} (code {kind.code}) clashes with {other.name!r} (code {other.code})")
    for name, (code, _module) in SHIPPED.items():  # a shipped kind not imported yet keeps its name and code
        if (name == kind.name) != (code == kind.code) and name not in _BY_NAME:
            raise ValueError(f"kind {kind.name!r} (code {kind.code}) clashes with {name!r} (code {code})")
    _BY_NAME[kind.name] = kind
    _BY_CODE[kind.code] = kind
    return kind


def _shipped(name: str) -> PolicyKind | None:
    """The shipped kind `name`, its package imported and registered now (None: not a shipped kind)."""
    entry = SHIPPED.get(name)
    if entry is None:
        return None
    code, module = entry
    with _LOADING:
        kind = _BY_NAME.get(name)
        if kind is None:
            kind = importlib.import_module(module).KIND
            if not isinstance(kind, PolicyKind) or (kind.name, kind.code) != (name, code):
                raise ImportError(f"{module}.KIND is not the {name!r} kind (code {code})")
            register(kind)
    return kind


def of_code(code: int) -> PolicyKind | None:
    kind = _BY_CODE.get(code)
    if kind is not None:
        return kind
    name = next((n for n, (c, _m) in SHIPPED.items() if c == code), None)
    return _shipped(name) if name is not None else None


def of_name(name: str) -> PolicyKind:
    """The kind called `name`; KeyError naming the known ones if there is none."""
    kind = _BY_NAME.get(name) or _shipped(name)
    if kind is None:
        raise KeyError(f"unknown policy kind {name!r} (known: {', '.join(names())})")
    return kind


def of_policy(policy: Policy) -> PolicyKind:
    return of_name(policy.kind)


def names() -> list[str]:
    """Every kind's name: the shipped ones (imported or not) and those registered."""
    return sorted(set(_BY_NAME) | set(SHIPPED))
