"""What a test prints when our processes did not stop in time: each one's thread stacks (SIGUSR1:
firmware_py.stackdump, registered by qnav, qnav-robot and qnav-sim; they go to the process's stderr,
which for the children of a run is its log in the run folder) and the tails of the run folder's logs."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from pathlib import Path


def stacks_and_logs(pids: list[int], folder: Path, lines: int = 60) -> str:
    """SIGUSR1 to each live pid, a moment for the dumps to be written, then the last `lines` of every
    *.log under `folder` (children's stderr)."""
    for pid in pids:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGUSR1)
    time.sleep(1.5)
    parts = []
    for log in sorted(folder.rglob("*.log")) if folder.is_dir() else []:
        with contextlib.suppress(OSError):
            tail = log.read_text(errors="replace").splitlines()[-lines:]
            parts.append(f"--- {log} (last {len(tail)} lines)\n" + "\n".join(tail))
    return "\n".join(parts) or f"(no logs under {folder})"
