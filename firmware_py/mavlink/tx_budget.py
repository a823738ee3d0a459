"""What a serial link may carry: the robot's transmit budget per link.

A 57600-baud radio moves 5760 bytes/s. The telemetry streams' rates are the robot's (and a ground
station may raise any of them with SET_MESSAGE_INTERVAL), and in HIL the robot's clock can run
faster than the wall's, so the streams can ask for more than the radio carries; the radio's buffer
then queues every reply (COMMAND_ACK, PARAM_VALUE, FTP) behind seconds of stale telemetry. ArduPilot
checks the port's free transmit space before each stream message and skips it when there is none;
`TxBudget` does the same for the robot: a token bucket of `share` x baud / 10 bytes per second of
**wall** time (the radio is physical), at most `burst_s` of it saved up. Every frame spends its
bytes; a stream message is sent only when the bucket is not in debt, so replies, heartbeats and
STATUSTEXTs always go and telemetry thins out to what is left. Network links have no budget.
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
