"""`qnav bench NAME`: benchmarks, one module each in `ground_station.bench`.

A benchmark prints a table and writes JSON; every speed figure comes with a
baseline measured in the same run and their ratio.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil

from ground_station import bench


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark (prints a table, writes JSON)",
                       description=__doc__)
    inner = p.add_subparsers(dest="bench", metavar="NAME")
    inner.required = True
    for info in sorted(pkgutil.iter_modules(bench.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"{bench.__name__}.{info.name}")
        if hasattr(module, "add_subparser"):
            module.add_subparser(inner)
