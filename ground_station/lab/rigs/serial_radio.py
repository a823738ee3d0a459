"""An emulated serial telemetry radio pair (SiK-like) between two pseudo-terminals.

Each side gets a pty (`os.openpty`): the robot opens `robot_device`
(`qnav-robot --mavlink /dev/pts/N --mavlink-baud 57600`), the ground station
`gcs_device` (`qnav ... --mavlink /dev/pts/M,57600`). Bytes written on one
side come out of the other at the radio's rate: each byte occupies the air
for `bits_per_byte / baud` seconds (10 bits for 8N1; the pty itself has no
rate), per direction, queued like in a radio's buffer, then `latency_s`.

Like SiK firmware with MAVLink framing on, the radio sends whole MAVLink
frames (v1 0xFE and v2 0xFD, signed or not) as air packets: `loss` drops a
packet (its air time still used), `byte_loss` drops single bytes inside
packets (a corrupted frame the receiver's CRC rejects). Bytes that are not a
MAVLink frame pass as they come (a partial frame is sent after 20 ms).
The draws come from a seeded RNG per direction, as in link_emulator.py.

The emulator keeps each pty's slave end open itself, so a ground station
may close and reopen its device between commands (like unplugging a USB
radio would not do, but like a radio left powered does); bytes for a side
whose reader lags are held by the pty and dropped (counted in `overflowed`)
once the kernel's buffer is full.

    with SerialRadio(LinkConfig(loss=0.0)) as radio:
        robot: --mavlink {radio.robot_device} --mavlink-baud 57600
        qnav upload --mavlink {radio.gcs_device},57600 ...
"""

from __future__ import annotations

import contextlib
import errno
import heapq
import os
import time
import tty
from dataclasses import dataclass

from ground_station.lab.rigs.link_emulator import DOWN, UP, LinkConfig, RadioRelay

PARTIAL_FLUSH_S = 0.02


@dataclass
class RadioConfig(LinkConfig):
    byte_loss: float = 0.0  # probability each byte of a packet is lost

    def validate(self) -> None:
        super().validate()
        if not 0.0 <= self.byte_loss <= 1.0:
            raise ValueError(f"byte_loss must be within 0..1, got {self.byte_loss}")


def split_frames(buf: bytearray) -> tuple[list[bytes], int]:
    """Complete MAVLink frames (and stray bytes) at the front of `buf`; (packets, bytes used)."""
    out: list[bytes] = []
    i = 0
    n = len(buf)
    while i < n:
        b = buf[i]
        if b == 0xFD:
            if n - i < 3:
                break
            size = 10 + buf[i + 1] + 2 + (13 if buf[i + 2] & 0x01 else 0)
        elif b == 0xFE:
            if n - i < 2:
                break
            size = 6 + buf[i + 1] + 2
        else:
            j = i
            while j < n and buf[j] not in (0xFD, 0xFE):
                j += 1
            out.append(bytes(buf[i:j]))
            i = j
            continue
        if n - i < size:
            break
        out.append(bytes(buf[i:i + size]))
        i += size
    return out, i


class SerialRadio(RadioRelay):
    """See the module docstring. Use as a context manager."""

    THREAD_NAME = "serial-radio"
    config: RadioConfig

    def __init__(self, config: RadioConfig | LinkConfig | None = None) -> None:
        cfg = config or RadioConfig()
        if not isinstance(cfg, RadioConfig):
            cfg = RadioConfig(**vars(cfg))
        super().__init__(cfg)
        self._masters: list[int] = []
        self._slaves: list[int] = []
        self.devices: list[str] = []
        for _side in range(2):  # 0 ground station, 1 robot
            master, slave = os.openpty()
            tty.setraw(slave)  # no echo, no line editing: binary as is, before anyone opens it
            os.set_blocking(master, False)
            self._masters.append(master)
            self._slaves.append(slave)
            self.devices.append(os.ttyname(slave))
        self._rx = [bytearray(), bytearray()]
        self._rx_since = [0.0, 0.0]
        self.bytes_lost = [0, 0]
        self._sides = self._masters
        self._wake_r, self._wake_w = os.pipe()

    @property
    def gcs_device(self) -> str:
        return self.devices[0]

    @property
    def robot_device(self) -> str:
        return self.devices[1]

    def _wake(self) -> None:
        os.write(self._wake_w, b"x")

    def _close(self) -> None:
        for fd in (*self._masters, *self._slaves, self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)

    def _schedule(self, direction: int, packet: bytes, now: float) -> None:
        cfg = self.config
        st = self.stats.of(direction)
        rng = self._rng[direction]
        r_loss = rng.random()
        airtime = len(packet) / cfg.bytes_per_s
        start = self._take_air(direction, len(packet), now)
        if start is None:
            return
        if r_loss < cfg.loss:
            st.lost += 1
            return
        if cfg.byte_loss:
            kept = bytes(b for b in packet if rng.random() >= cfg.byte_loss)
            self.bytes_lost[direction] += len(packet) - len(kept)
            packet = kept
        self._counter += 1
        heapq.heappush(self._heap, (start + airtime + cfg.latency_s, self._counter, direction, packet))

    def _read_side(self, side: int) -> None:
        now = time.monotonic()
        direction = UP if side == 0 else DOWN
        while True:
            try:
                data = os.read(self._masters[side], 4096)
            except BlockingIOError:
                break
            except OSError as exc:  # EIO: no slave open (cannot happen: we hold one) or closed
                if exc.errno != errno.EIO:
                    raise
                break
            if not data:
                break
            if not self._rx[side]:
                self._rx_since[side] = now
            self._rx[side] += data
        packets, used = split_frames(self._rx[side])
        if packets:
            del self._rx[side][:used]
            self._rx_since[side] = now
            for p in packets:
                self._schedule(direction, p, now)

    def _flush_partial(self, now: float) -> None:
        for side in (0, 1):
            if self._rx[side] and now - self._rx_since[side] >= PARTIAL_FLUSH_S:
                self._schedule(UP if side == 0 else DOWN, bytes(self._rx[side]), now)
                self._rx[side].clear()

    def _send_due(self, now: float) -> float | None:
        self._flush_partial(now)
        while self._heap and self._heap[0][0] <= now:
            _t, _n, direction, packet = heapq.heappop(self._heap)
            out = self._masters[1 if direction == UP else 0]
            st = self.stats.of(direction)
            try:
                written = os.write(out, packet)
            except BlockingIOError:
                written = 0
            except OSError:
                written = 0
            if written < len(packet):
                st.overflowed += 1
            else:
                st.delivered += 1
        waits = [self._heap[0][0] - now] if self._heap else []
        waits += [PARTIAL_FLUSH_S for side in (0, 1) if self._rx[side]]
        return max(0.0, min(waits)) if waits else None
