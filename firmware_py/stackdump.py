"""`kill -USR1 PID` prints every thread's Python stack to stderr (the robot's, the sim's and the
station's programs register it at start): a process that does not stop, or stops answering, says
where it is without being stopped (systemd's journal or the run folder's log keeps the dump)."""

from __future__ import annotations

import contextlib
import faulthandler
import io
import signal
import sys


def dump_stacks_on_sigusr1() -> None:
    """Register faulthandler on SIGUSR1; a no-op where stderr has no file descriptor (in-process
    callers under a capturing test) or the platform has no SIGUSR1."""
    with contextlib.suppress(OSError, ValueError, AttributeError, io.UnsupportedOperation):
        faulthandler.register(signal.SIGUSR1, file=sys.stderr, all_threads=True)
