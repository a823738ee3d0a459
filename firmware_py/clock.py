"""The robot's one clock.

Every timeout on the robot (sensor staleness, motor watchdog feed, GCS
heartbeat, FTP session expiry) reads the same `Clock`. On a real robot that
is the monotonic wall clock; in hardware-in-the-loop runs the sim owns time
and the controller advances a `SimClock` from the sim's tick frames, so
timeouts are measured in sim time, never wall time.

All values are integer microseconds.

Sim time is input from the bus, so it is checked (hostile testing, issue
13): once a `SimClock` has taken its first tick, a tick more than
`max_jump_us` (MAX_TICK_JUMP_US, 250 ms: the default sensor staleness
timeout) ahead of the clock is refused and counted in `refused_jumps`,
unless RESYNC_TICKS consecutive ticks agree on the new time (each ahead of
the previous by at most the bound: the sim really jumped, e.g. ticks lost in
paced mode). One forged far-future SimTick therefore neither stops the robot
(paced mode would wait for a control deadline in the far future) nor
freezes its clock (lockstep: the clock would stick ahead and staleness
would never be seen again). A first tick is always taken, so a robot that
starts while the sim runs joins it.
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


MAX_TICK_JUMP_US = 250_000
RESYNC_TICKS = 3


class SimClock(Clock):
    """Time set from outside (sim tick frames); never goes backwards, never
    jumps ahead by more than `max_jump_us` on one tick's word (module doc)."""

    def __init__(self, start_us: int = 0, *, max_jump_us: int = MAX_TICK_JUMP_US) -> None:
        self._now = start_us
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self.max_jump_us = max_jump_us
        self.refused_jumps = 0
        self._synced = False  # the first tick is taken whatever it says
        self._candidates: list[int] = []  # consecutive too-far ticks agreeing with each other

    def now_us(self) -> int:
        return self._now

    def set_us(self, t_us: int) -> bool:
        """Advance to `t_us`; earlier values are ignored (frames can arrive
        late). False if `t_us` was refused as an implausible jump."""
        with self._changed:
            if self._synced and t_us - self._now > self.max_jump_us:
                c = self._candidates
                if c and 0 < t_us - c[-1] <= self.max_jump_us:
                    c.append(t_us)
                else:
                    self._candidates = c = [t_us]
                if len(c) < RESYNC_TICKS:
                    self.refused_jumps += 1
                    return False
            self._candidates = []
            self._synced = True
            if t_us > self._now:
                self._now = t_us
                self._changed.notify_all()
            return True

    def advance_us(self, dt_us: int) -> None:
        """Advance by `dt_us` (a local, trusted step: no jump check)."""
        with self._changed:
            if dt_us > 0:
                self._now += dt_us
                self._changed.notify_all()

    def wait_until(self, t_us: int, timeout_s: float | None = None) -> bool:
        """Block until sim time reaches `t_us` (wall `timeout_s` as a guard)."""
        with self._changed:
            return self._changed.wait_for(lambda: self._now >= t_us, timeout_s)
