"""The robot's one clock.

Every timeout on the robot (sensor staleness, motor watchdog feed, GCS
heartbeat, FTP session expiry) reads the same `Clock`. On a real robot that
is the monotonic wall clock; in hardware-in-the-loop runs the sim owns time
and the controller advances a `SimClock` from the sim's tick frames, so
timeouts are measured in sim time, never wall time.

All values are integer microseconds.
"""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod


class Clock(ABC):
    """Monotonic time source in integer microseconds."""

    @abstractmethod
    def now_us(self) -> int:
        """Current time in microseconds (monotonic, arbitrary origin)."""

    def now_s(self) -> float:
        return self.now_us() / 1e6


class WallClock(Clock):
    """The host's monotonic clock."""

    def __init__(self) -> None:
        self._origin = time.monotonic_ns()

    def now_us(self) -> int:
        return (time.monotonic_ns() - self._origin) // 1000


class SimClock(Clock):
    """Time set from outside (sim tick frames); never goes backwards."""

    def __init__(self, start_us: int = 0) -> None:
        self._now = start_us
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)

    def now_us(self) -> int:
        return self._now

    def set_us(self, t_us: int) -> None:
        """Advance to `t_us`; earlier values are ignored (frames can arrive late)."""
        with self._changed:
            if t_us > self._now:
                self._now = t_us
                self._changed.notify_all()

    def advance_us(self, dt_us: int) -> None:
        self.set_us(self._now + dt_us)

    def wait_until(self, t_us: int, timeout_s: float | None = None) -> bool:
        """Block until sim time reaches `t_us` (wall `timeout_s` as a guard)."""
        with self._changed:
            return self._changed.wait_for(lambda: self._now >= t_us, timeout_s)
