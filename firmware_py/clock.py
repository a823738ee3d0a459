"""The robot's one clock.

Every timeout on the robot (sensor staleness, motor watchdog feed, GCS heartbeat, FTP session
expiry) reads the same `Clock`. On a real robot that is the monotonic wall clock; in
hardware-in-the-loop runs the sim owns time and the controller advances a `SimClock` from the sim's
tick frames, so timeouts are measured in sim time, never wall time.

All values are integer microseconds.

Sim time is input from the bus, so it is checked: `SimClock` refuses a jump ahead (its first tick is
always taken, so a robot joins a running sim): docs/can-protocol.md, "Time and the lockstep handshake".

Before that, `TickGate` checks the sim's protocol: counter and time advance together, one control
period per count (learnt from the first two consecutive ticks), within a quarter period. A tick that
skips counts is what a lockstep sim sends after giving up on an answer, resent until answered: it is
taken after RESYNC_TICKS identical copies in lockstep, at once when paced; at most MAX_TICK_GAP
counts per step. A frame on the bus is not authenticated, so a forger can still send the next
consistent tick first.
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

class WallClock(Clock):
    """The host's monotonic clock."""

    def __init__(self) -> None:
        self._origin = time.monotonic_ns()

    def now_us(self) -> int:
        return (time.monotonic_ns() - self._origin) // 1000


MAX_TICK_JUMP_US = 250_000
RESYNC_TICKS = 3
MAX_TICK_GAP = 64  # counts skipped in one step: a lockstep sim skips one per tick timeout (1 s)


class TickGate:
    """Which SimTicks may move the clock (module doc). Pure: the caller gives
    each tick's counter, its time and its counter gap from the last taken tick,
    and calls `taken` for a tick the clock then took."""

    def __init__(self, *, max_gap: int = MAX_TICK_GAP) -> None:
        self.max_gap = max_gap
        self.period_us: int | None = None  # the sim's time per count, learnt
        self.refused = 0
        self._last_us: int | None = None
        self._resend: tuple[int, int] = (-1, -1)  # (counter, time) of a tick skipping counts
        self._copies = 0

    def admit(self, counter: int, sim_us: int, gap: int, *, resends: bool) -> bool:
        """True if the tick may step the clock; `resends`: the sim resends an
        unanswered tick (lockstep), so a skip must be confirmed by its copies."""
        last = self._last_us
        if last is None or gap == 0:
            return True
        dt = sim_us - last
        if self.period_us is None:
            if gap == 1 and 0 < dt <= MAX_TICK_JUMP_US:
                self.period_us = dt
                return True
            return self._refuse()
        if gap > self.max_gap or abs(dt - gap * self.period_us) > self.period_us // 4:
            return self._refuse()
        if gap > 1 and resends:
            if self._resend == (counter, sim_us):
                self._copies += 1
            else:
                self._resend, self._copies = (counter, sim_us), 1
            if self._copies < RESYNC_TICKS:
                return self._refuse()
        return True

    def taken(self, sim_us: int) -> None:
        """The clock took the tick at `sim_us`: the next gap counts from it."""
        self._last_us = sim_us
        self._resend, self._copies = (-1, -1), 0

    def _refuse(self) -> bool:
        self.refused += 1
        return False


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
