"""How many jobs a `firmware_py.background.Background` holds not started yet (the tests' look at
what a tick asked for; the robot only posts jobs and runs them)."""

from __future__ import annotations

from firmware_py.background import Background


def pending(work: Background) -> int:
    with work._cv:
        return len(work._jobs)
