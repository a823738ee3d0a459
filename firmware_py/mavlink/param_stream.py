"""PARAM_REQUEST_LIST answered in the background, at a bounded rate (as ArduPilot streams it).

A request only (re)starts its requester's stream at index 0; `due(now_us)` hands out the next
indices under one token bucket, round-robin over at most MAX_STREAMS requesters (a new one beyond
that replaces the longest-waiting). Why (a list answered at once is an amplifier): docs/mavlink.md,
"Parameters". Pure: the caller's clock, no I/O.
"""

from __future__ import annotations

from collections import OrderedDict

RATE_HZ = 500  # PARAM_VALUEs a second over UDP/TCP (~18 kB/s)
SERIAL_RATE_HZ = 50  # over a 57600-baud radio (~1.9 kB/s of its 5.8)
BURST = 32  # a whole list (31 parameters today) in one go when the bucket is full
MAX_STREAMS = 4

Requester = tuple[int, int]  # (system id, component id)


class ParamStream:
    """Per-requester list streams under one token bucket."""

    def __init__(self, rate_hz: int = RATE_HZ, burst: int = BURST, max_streams: int = MAX_STREAMS) -> None:
        self.rate_hz = rate_hz
        self.burst = burst
        self.max_streams = max_streams
        self._next: OrderedDict[Requester, int] = OrderedDict()  # requester -> next index to send
        self._tokens = float(burst)
        self._last_us: int | None = None
        self.requests = 0
        self.restarted = 0  # requests that restarted a stream still running
        self.evicted = 0  # streams dropped for a new requester (MAX_STREAMS)

    @property
    def active(self) -> int:
        return len(self._next)

    def request(self, requester: Requester) -> None:
        """(Re)start `requester`'s stream at index 0."""
        self.requests += 1
        if requester in self._next:
            self.restarted += 1  # back to index 0, keeping its place in the round
        elif len(self._next) >= self.max_streams:
            self._next.popitem(last=False)
            self.evicted += 1
        self._next[requester] = 0

    def due(self, now_us: int, count: int) -> list[tuple[Requester, int]]:
        """The (requester, index) pairs to send now, within the rate; streams of `count` parameters."""
        if self._last_us is not None and now_us > self._last_us:
            self._tokens = min(float(self.burst), self._tokens + (now_us - self._last_us) * self.rate_hz / 1e6)
        self._last_us = now_us if self._last_us is None else max(self._last_us, now_us)
        out: list[tuple[Requester, int]] = []
        while self._next and self._tokens >= 1.0:
            for requester in list(self._next):
                if self._tokens < 1.0:
                    break
                index = self._next[requester]
                if index >= count:
                    del self._next[requester]
                    continue
                out.append((requester, index))
                self._tokens -= 1.0
                if index + 1 >= count:
                    del self._next[requester]
                else:
                    self._next[requester] = index + 1
        return out
