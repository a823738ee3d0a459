"""`qnav study`: research beside the product; its options and run are
`ground_station.lab.cli.study`."""

from __future__ import annotations

import argparse


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.lab.cli import study

    study.add_subparser(sub)
