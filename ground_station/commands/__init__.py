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


def add_actions(sub: argparse._SubParsersAction, name: str, help: str, description: str | None, dest: str,
                metavar: str = "ACTION") -> argparse._SubParsersAction:
    """Subcommand `name` made of actions (`qnav param list`, `qnav policy inspect`): its parser
    (the description printed as written) and the actions' subparsers, one of them required, the
    chosen one's name in `dest`."""
    p = sub.add_parser(name, help=help, description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    return p.add_subparsers(dest=dest, metavar=metavar, required=True)
