"""Session-wide set-up for the suite: only what every test relies on.

SIGINT: many tests stop a program the way an operator does, with Ctrl-C
(SIGINT), and check that it wrote its outputs. A process started in the
background by a non-interactive shell (`make test &`, some CI runners)
inherits SIGINT *ignored*, and an ignored signal stays ignored across exec,
so every program the tests start would ignore Ctrl-C and be killed after the
grace period instead (seen: `qnav sitl`, `qnav demo`, `qnav-robot` all
SIGKILLed, stats never written). Catching SIGINT here, before pytest-xdist
starts its workers, makes the children start with the default disposition.
"""

from __future__ import annotations

import signal


def pytest_configure(config) -> None:
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
