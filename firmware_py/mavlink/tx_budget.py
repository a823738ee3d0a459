"""What a serial link may carry: the robot's transmit budget per link.

`TxBudget` is a token bucket of `share` x baud / 10 bytes per second of **wall** time (the radio is
physical), at most `burst_s` of it saved up: every frame spends its bytes, and a stream message is
sent only when the bucket is not in debt, so replies, heartbeats and STATUSTEXTs always go and the
telemetry thins out to what is left, as ArduPilot skips a stream message when the port has no
transmit space. Why (a radio's buffer queues every reply behind stale telemetry) and what it
measured: docs/mavlink.md, "Messages sent". Network links have no budget.
"""

from __future__ import annotations

import time
from collections.abc import Callable

MAVLINK2_OVERHEAD = 12 + 2  # header + checksum
SIGNATURE_LEN = 13
TELEMETRY_SHARE = 0.8  # of the raw byte rate: headroom for the radio's own framing and retries
BURST_S = 0.5


class TxBudget:
    def __init__(self, bytes_per_s: float, burst_s: float = BURST_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not bytes_per_s > 0:
            raise ValueError(f"bytes_per_s must be positive, got {bytes_per_s}")
        self.rate = bytes_per_s
        self.cap = bytes_per_s * burst_s
        self.clock = clock
        self.tokens = self.cap
        self._t = clock()
        self.dropped = 0  # stream messages skipped

    @classmethod
    def for_baud(cls, baud: int, share: float = TELEMETRY_SHARE, **kw: object) -> TxBudget:
        """The budget of a serial line at `baud` (8N1: 10 bits a byte)."""
        return cls(share * baud / 10.0, **kw)  # type: ignore[arg-type]

    def _refill(self) -> None:
        now = self.clock()
        self.tokens = min(self.cap, self.tokens + (now - self._t) * self.rate)
        self._t = now

    def allow(self, nbytes: int, stream: bool) -> bool:
        """Whether to send a frame of `nbytes`; spends them when it is sent.
        Non-stream frames are always sent (the bucket may go into debt);
        a stream frame only when the bucket is not in debt."""
        self._refill()
        if stream and self.tokens < nbytes:
            self.dropped += 1
            return False
        self.tokens -= nbytes
        return True


def frame_len(msg: object, signed: bool) -> int:
    """Upper bound of a MAVLink 2 frame's length for a pymavlink message
    (payload untrimmed)."""
    size = getattr(getattr(type(msg), "unpacker", None), "size", 0) or 0
    return MAVLINK2_OVERHEAD + int(size) + (SIGNATURE_LEN if signed else 0)
