"""`qnav` subcommands, one module each (see `ground_station.cli`)."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
from types import ModuleType


def add_module_subparsers(sub: argparse._SubParsersAction, package: ModuleType, only: str | None = None) -> None:
    """Every module of `package` exposing `add_subparser(sub)` becomes a subcommand, in name order.
    With `only` naming one of them (a module's `COMMANDS`, else its name), that one alone (a parser
    may import much); a name no module has builds them all, so argparse lists the choices."""
    modules = [importlib.import_module(f"{package.__name__}.{info.name}")
               for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda m: m.name)]
    modules = [m for m in modules if hasattr(m, "add_subparser")]
    chosen = [m for m in modules if only in getattr(m, "COMMANDS", (m.__name__.rpartition(".")[2],))]
    for module in chosen or modules:
        module.add_subparser(sub)


def add_actions(sub: argparse._SubParsersAction, name: str, help: str, description: str | None, dest: str,
                metavar: str = "ACTION") -> argparse._SubParsersAction:
    """Subcommand `name` made of actions (`qnav param list`, `qnav policy inspect`): its parser
    (the description printed as written) and the actions' subparsers, one of them required, the
    chosen one's name in `dest`."""
    p = sub.add_parser(name, help=help, description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    return p.add_subparsers(dest=dest, metavar=metavar, required=True)
