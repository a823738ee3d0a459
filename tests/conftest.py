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
    """The longest tests first: the UML vcan batch (`xdist_group`, a chain on one worker) and the
    `slow` integration runs, the slow ones by their timeout, the longest allowed first; then the
    rest in their order; the Ray cluster's chain (`ray`) last. pytest-xdist hands out work in
    collection order, and a long test that starts last is the run's tail on its own (docs/commands
    and faults come last alphabetically). The Ray chain is the exception: a cluster of a dozen
    processes starved beside the page runs (both Ray tests hit their 300 s timeout when it ran
    first beside two busy processes); at the end it has the cores the other workers give up. A
    stable sort, so tests keep their relative order within each class."""

    def rank(item) -> tuple[int, float]:
        if item.get_closest_marker("ray") is not None:
            return 3, 0.0
        if item.get_closest_marker("xdist_group") is not None:
            return 0, 0.0
        if item.get_closest_marker("slow") is None:
            return 2, 0.0
        timeout = item.get_closest_marker("timeout")
        return 1, -float(timeout.args[0]) if timeout and timeout.args else 0.0

    items.sort(key=rank)
