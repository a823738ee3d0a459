"""The policies shipped with qnav, found by name.

`shipped_policy("sector")` is the path of `sector.qtab`; `resolve_policy_spec` turns a
`policies:NAME` spec into that path and leaves any other value as a file path, so every option that
takes a policy file also takes a shipped policy by name (`qnav-robot --policy policies:sector`,
`qnav policy inspect policies:paper10_cell`).

The source of truth is the checkout's top-level `policies/` folder. The wheel ships that folder as
the package `qnav_policies` (setup.py), so an installed qnav finds the policies without a checkout;
run from a checkout (PYTHONPATH or an editable install) the folder beside this package is used, so a
worktree sees its own files. Stdlib only.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

SPEC_PREFIX = "policies:"
PACKAGE = "qnav_policies"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


class ShippedPolicyError(ValueError):
    """A shipped policy that does not exist (or a broken install); the text is one line."""


def shipped_policies_dir() -> Path:
    """The folder holding the shipped `.qtab` files."""
    checkout = Path(__file__).resolve().parents[1]
    # a checkout has pyproject.toml beside the packages; site-packages does not
    if (checkout / "pyproject.toml").is_file() and (checkout / "policies" / "__init__.py").is_file():
        return checkout / "policies"
    try:
        spec = importlib.util.find_spec(PACKAGE)
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.submodule_search_locations:
        raise ShippedPolicyError(f"the shipped policies are not installed (no package {PACKAGE}): reinstall qnav")
    return Path(next(iter(spec.submodule_search_locations)))


def shipped_policy_names() -> list[str]:
    """Names of the shipped policies, sorted (`paper10_cell`, `sector`, ...)."""
    return sorted(p.stem for p in shipped_policies_dir().glob("*.qtab"))


def shipped_policy(name: str) -> Path:
    """Path of the shipped policy NAME (`sector` or `sector.qtab`)."""
    stem = name[:-5] if name.endswith(".qtab") else name
    path = shipped_policies_dir() / f"{stem}.qtab"
    if not _NAME.fullmatch(stem) or not path.is_file():
        raise ShippedPolicyError(f"no shipped policy {name!r} (shipped: {', '.join(shipped_policy_names()) or 'none'})")
    return path


def resolve_policy_spec(spec: str | Path) -> Path:
    """`policies:NAME` -> the shipped file; anything else is a file path, returned as a Path."""
    if isinstance(spec, str) and spec.startswith(SPEC_PREFIX):
        return shipped_policy(spec[len(SPEC_PREFIX):])
    return Path(spec)


def policy_file_arg(text: str) -> Path:
    """argparse `type=` for an option taking a policy: a path, or `policies:NAME`."""
    import argparse

    try:
        return resolve_policy_spec(text)
    except ShippedPolicyError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
