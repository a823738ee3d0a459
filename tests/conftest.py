"""Session-wide set-up for the suite: only what every test relies on, and the order tests run in.

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


def pytest_collection_modifyitems(config, items) -> None:
    """The longest tests first: the grouped ones (`xdist_group`: the Ray cluster's and the UML vcan
    batch's, each a chain on one worker) and the `slow` integration runs, then the rest in their
    order; the slow ones by their timeout, the longest allowed first. pytest-xdist hands out
    work in collection order, and a long test that starts last is the run's tail on its own
    (docs/commands and faults come last alphabetically); a stable sort, so tests keep their
    relative order within each class."""

    def rank(item) -> tuple[int, float]:
        if item.get_closest_marker("xdist_group") is not None:
            return 0, 0.0
        if item.get_closest_marker("slow") is None:
            return 2, 0.0
        timeout = item.get_closest_marker("timeout")
        return 1, -float(timeout.args[0]) if timeout and timeout.args else 0.0

    items.sort(key=rank)
