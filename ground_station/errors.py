"""The ground station's user-facing error, shared by the library and the CLI.

Library code (learning, rigs, benchmarks, the MAVLink client) raises
`CliError` for what the user got wrong or what the robot refused; `qnav`
prints it as one line and exits 2. It lives here, not in `cli.py`, so no
library module imports the command line.
"""

from __future__ import annotations


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""
