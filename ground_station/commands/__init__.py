"""`qnav` subcommands, one module each (see `ground_station.cli`)."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
from types import ModuleType


def add_module_subparsers(sub: argparse._SubParsersAction, package: ModuleType) -> None:
    """Every module of `package` exposing `add_subparser(sub)` becomes a subcommand, in name order."""
    for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{package.__name__}.{info.name}")
        if hasattr(module, "add_subparser"):
            module.add_subparser(sub)
