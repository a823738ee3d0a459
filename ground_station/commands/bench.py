"""`qnav bench NAME`: benchmarks, one module each in `ground_station.lab.bench`.

A benchmark prints a table and writes JSON; every speed figure comes with a
baseline measured in the same run and their ratio.
"""

from __future__ import annotations

import argparse

from ground_station.commands import add_module_subparsers
from ground_station.lab import bench


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark (prints a table, writes JSON)",
                       description=__doc__)
    add_module_subparsers(p.add_subparsers(dest="bench", metavar="NAME", required=True), bench)
