"""HIL rigs, the throwaway Ray cluster and the process helpers they and the tests share."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path


def other_processes() -> Iterator[tuple[int, str]]:
    """(pid, command line, its NULs as spaces) of every live process but this one (Linux
    /proc); a process that ends while it is read is passed over."""
    me = os.getpid()
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == me:
            continue
        try:
            cmd = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        yield int(entry), cmd
