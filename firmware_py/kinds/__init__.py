"""Policy kinds: one module per kind of `.qtab` policy the robot runs, and the one
registry that maps a kind's name and file code to it (as python-can maps an
interface name to its bus class).

Shipped: `cell` (the paper's grid state; firmware_py.kinds.cell), `sector`
(bearing sector x range bins, steering on the local planner's sub-goals;
firmware_py.kinds.sector) and `sector-memory` (the cell-stepped Bug memory;
firmware_py.kinds.sector_memory). The loader (`firmware_py.policy`), the writer
and the controller find a kind only through `of_code`, `of_name` and
`of_policy`; a new kind is a module with a `PolicyKind` passed to `register`.

Kind codes of experiments removed from qnav (docs/research.md; commit e026a1b has them) are reserved in
`REMOVED`: never reused, and a file of one is refused by name.
"""

from __future__ import annotations

from firmware_py.kinds.base import Decision, DriveTick, KindDriver, Policy, PolicyKind, Unpacked

__all__ = ["Decision", "DriveTick", "KindDriver", "PolicyKind", "Unpacked", "REMOVED", "REMOVED_AT",
           "register", "unregister", "of_code", "of_name", "of_policy", "names"]

REMOVED = {3: "sector-memory-tick", 5: "sector-unmapped"}
REMOVED_AT = "e026a1b"  # the last commit that has them (docs/research.md)

_BY_NAME: dict[str, PolicyKind] = {}
_BY_CODE: dict[int, PolicyKind] = {}


def register(kind: PolicyKind) -> PolicyKind:
    """Make `kind` known to the loader, the writer and the controller; returns it."""
    if kind.code in REMOVED:
        raise ValueError(f"kind code {kind.code} belonged to {REMOVED[kind.code]} and is not reused")
    for other in (_BY_NAME.get(kind.name), _BY_CODE.get(kind.code)):
        if other is not None and other is not kind:
            raise ValueError(f"kind {kind.name!r} (code {kind.code}) clashes with {other.name!r} (code {other.code})")
    _BY_NAME[kind.name] = kind
    _BY_CODE[kind.code] = kind
    return kind


def unregister(name: str) -> None:
    """Forget a kind (tests that register a toy kind clean up with this)."""
    kind = _BY_NAME.pop(name, None)
    if kind is not None:
        _BY_CODE.pop(kind.code, None)


def of_code(code: int) -> PolicyKind | None:
    return _BY_CODE.get(code)


def of_name(name: str) -> PolicyKind:
    """The kind called `name`; KeyError naming the known ones if there is none."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise KeyError(f"unknown policy kind {name!r} (known: {', '.join(names())})") from None


def of_policy(policy: Policy) -> PolicyKind:
    return of_name(policy.kind)


def names() -> list[str]:
    return sorted(_BY_NAME)


def _register_shipped() -> None:
    from firmware_py.kinds import cell, sector, sector_memory

    for module in (cell, sector, sector_memory):
        register(module.KIND)


_register_shipped()
