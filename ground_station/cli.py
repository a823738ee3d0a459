"""`qnav` command line: one module per subcommand.

Every module in `ground_station.commands` exposing
`add_subparser(subparsers)` becomes a subcommand; the subparser sets
`func=run(args) -> int`. Heavy imports live inside each command's `run` so a
broken optional dependency only fails the command that needs it.
"""

from __future__ import annotations

import argparse
import sys
from typing import NoReturn

from firmware_py.stackdump import dump_stacks_on_sigusr1
from ground_station import commands
from ground_station.commands import add_module_subparsers
from ground_station.errors import CliError
from ground_station.extras import require_station


class OneLineErrorParser(argparse.ArgumentParser):
    """Usage errors in one line, naming what is wrong and where the help is (not the usage
    block first); subcommand parsers are of this class too (argparse builds them with the
    parent's class)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The `qnav` parser; given the command about to run, only its subparser is built (see
    `add_module_subparsers`), which keeps `qnav arm` from importing the benchmarks."""
    parser = OneLineErrorParser(
        prog="qnav", description="qnav ground station: train, evaluate, export, upload, command, monitor.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    add_module_subparsers(sub, commands, only=command)
    return parser


def main(argv: list[str] | None = None) -> int:
    require_station("qnav")  # before the commands import numpy & co.: one line, not a traceback
    argv = sys.argv[1:] if argv is None else argv
    # the first word not an option is the command (qnav has no options of its own but -h)
    args = build_parser(next((a for a in argv if not a.startswith("-")), None)).parse_args(argv)
    dump_stacks_on_sigusr1()
    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"qnav {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
