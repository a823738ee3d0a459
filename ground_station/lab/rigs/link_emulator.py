#!/usr/bin/env python3
"""UDP relay that behaves like a telemetry radio between a ground station and
the robot: byte-rate limit (default 57600 baud 8N1 = 5760 B/s each way),
fixed latency, loss, duplication and reordering, all drawn from seeded RNGs.

Each UDP datagram is one MAVLink frame. Per direction, a frame occupies the
"air" for len/rate seconds after the previous one (frames queue like in a
radio's buffer), then arrives `latency` later. Lost frames still use their
air time; duplicates use it twice. Every frame draws the same three random
numbers (loss, duplicate, reorder) from its direction's RNG, so the same
traffic gets the same fate for the same seed.

Addresses: each side is a socket bound to 127.0.0.1. A side's peer is either
fixed (the peer listens: pymavlink `udpin`) or learnt from the first frame
it sends (the peer connects: pymavlink `udpout`).

Library:
    with LinkEmulator(gcs_peer=("127.0.0.1", 14550), config=LinkConfig(loss=0.05)) as link:
        robot connects udpout:127.0.0.1:{link.robot_port}

Tests that must lose one particular frame pass `drop(direction, frame) ->
bool` (library only): a frame it returns True for is lost like a random
loss (it still uses its air time), counted in `dropped`, and draws its
random numbers all the same, so the other frames keep their fates.

CLI: python -m ground_station.lab.rigs.link_emulator --help
"""

from __future__ import annotations

import argparse
import contextlib
import heapq
import random
import selectors
import socket
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Self

HOST = "127.0.0.1"
UP, DOWN = 0, 1  # UP: ground station -> robot, DOWN: robot -> ground station


@dataclass
class LinkConfig:
    baud: int = 57600
    bits_per_byte: int = 10  # 8N1: start + 8 data + stop
    latency_s: float = 0.0
    loss: float = 0.0  # probability a frame is lost, each direction
    duplicate: float = 0.0  # probability a frame arrives twice
    reorder: float = 0.0  # probability a frame is held back by reorder_delay_s
    reorder_delay_s: float = 0.05
    queue_bytes: int = 0  # radio buffer per direction; 0 = unbounded. Overflow drops.
    seed: int = 0

    @property
    def bytes_per_s(self) -> float:
        return self.baud / self.bits_per_byte

    def validate(self) -> None:
        for name in ("loss", "duplicate", "reorder"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be within 0..1, got {v}")
        if self.baud <= 0 or self.bits_per_byte <= 0:
            raise ValueError("baud and bits_per_byte must be positive")
        if self.latency_s < 0 or self.reorder_delay_s < 0 or self.queue_bytes < 0:
            raise ValueError("latency, reorder delay and queue size must not be negative")


@dataclass
class DirectionStats:
    frames_in: int = 0
    bytes_in: int = 0
    lost: int = 0
    dropped: int = 0  # by the `drop` predicate
    overflowed: int = 0
    duplicated: int = 0
    reordered: int = 0
    delivered: int = 0
    no_peer: int = 0


@dataclass
class LinkStats:
    up: DirectionStats = field(default_factory=DirectionStats)
    down: DirectionStats = field(default_factory=DirectionStats)

    def of(self, direction: int) -> DirectionStats:
        return self.up if direction == UP else self.down


class RadioRelay:
    """What a radio between the ground station and the robot keeps, whatever carries
    its bytes (`LinkEmulator`: UDP, `SerialRadio`: ptys): a seeded RNG and a radio queue
    per direction, the heap of frames in the air, the stats, and the relay thread
    (`_run`): it waits on the two sides (`_sides`, index 0 ground station, 1 robot)
    and `_wake_r`, reads a side that has bytes (`_read_side`) and sends what is due
    (`_send_due`, which says how long the thread may sleep); `stop` wakes it through
    `_wake`. A context manager: `start` on entry, `stop` on exit."""

    THREAD_NAME = "radio-relay"
    _sides: list[Any]  # file objects or descriptors a selector waits on
    _wake_r: Any

    def __init__(self, config: LinkConfig) -> None:
        config.validate()
        self.config = config
        self._rng = [random.Random(config.seed * 2 + 1), random.Random(config.seed * 2 + 2)]
        self._free_at = [0.0, 0.0]
        self._heap: list[tuple[float, int, int, bytes]] = []
        self._counter = 0
        self.stats = LinkStats()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def link_time(self, nbytes: int) -> float:
        """Seconds `nbytes` occupy one direction of the link."""
        return nbytes / self.config.bytes_per_s

    def start(self) -> Self:
        self._thread = threading.Thread(target=self._run, name=self.THREAD_NAME, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        with contextlib.suppress(OSError):
            self._wake()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _take_air(self, direction: int, nbytes: int, now: float) -> float | None:
        """Count a frame of `nbytes` into its direction's radio queue: when its air time
        starts (the queue's end moves past it), or None if the radio's buffer overflows (counted)."""
        cfg = self.config
        st = self.stats.of(direction)
        st.frames_in += 1
        st.bytes_in += nbytes
        start = max(now, self._free_at[direction])
        if cfg.queue_bytes and (start - now) * cfg.bytes_per_s + nbytes > cfg.queue_bytes:
            st.overflowed += 1
            return None
        self._free_at[direction] = start + nbytes / cfg.bytes_per_s
        return start

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._sides[0], selectors.EVENT_READ, 0)
        sel.register(self._sides[1], selectors.EVENT_READ, 1)
        sel.register(self._wake_r, selectors.EVENT_READ, -1)
        timeout: float | None = None
        while not self._stop.is_set():
            for key, _ev in sel.select(timeout):
                if key.data >= 0:
                    self._read_side(key.data)
            timeout = self._send_due(time.monotonic())
        sel.close()

    def _read_side(self, side: int) -> None:
        raise NotImplementedError

    def _send_due(self, now: float) -> float | None:
        raise NotImplementedError

    def _wake(self) -> None:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError


class LinkEmulator(RadioRelay):
    """See the module docstring. Ports 0 pick free ports (read them back)."""

    THREAD_NAME = "link-emulator"

    def __init__(self, config: LinkConfig | None = None, *, gcs_port: int = 0, robot_port: int = 0,
                 gcs_peer: tuple[str, int] | None = None, robot_peer: tuple[str, int] | None = None,
                 drop: Callable[[int, bytes], bool] | None = None) -> None:
        super().__init__(config or LinkConfig())
        self.drop = drop
        self._socks: list[socket.socket] = []
        for port in (gcs_port, robot_port):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((HOST, port))
            s.setblocking(False)
            self._socks.append(s)
        self._sides = self._socks
        self.gcs_port = self._socks[0].getsockname()[1]
        self.robot_port = self._socks[1].getsockname()[1]
        self._peers: list[tuple[str, int] | None] = [gcs_peer, robot_peer]  # index: side 0 gcs, 1 robot
        self._fixed = [gcs_peer is not None, robot_peer is not None]
        # a socketpair wakes the loop when stop() is called
        self._wake_r, self._wake_w = socket.socketpair()

    # --- lifecycle ---------------------------------------------------------------
    def _wake(self) -> None:
        self._wake_w.send(b"x")

    def _close(self) -> None:
        for s in (*self._socks, self._wake_r, self._wake_w):
            s.close()

    # --- the relay ---------------------------------------------------------------
    def _schedule(self, direction: int, data: bytes, now: float) -> None:
        cfg = self.config
        st = self.stats.of(direction)
        rng = self._rng[direction]
        r_loss, r_dup, r_reorder = rng.random(), rng.random(), rng.random()
        airtime = len(data) / cfg.bytes_per_s
        start = self._take_air(direction, len(data), now)
        if start is None:
            return
        copies = 2 if r_dup < cfg.duplicate else 1
        if copies == 2:
            st.duplicated += 1
            self._free_at[direction] += airtime
        if r_loss < cfg.loss:
            st.lost += 1
            return
        if self.drop is not None and self.drop(direction, data):
            st.dropped += 1
            return
        arrive = start + airtime + cfg.latency_s
        if r_reorder < cfg.reorder:
            st.reordered += 1
            arrive += cfg.reorder_delay_s
        for i in range(copies):
            self._counter += 1
            heapq.heappush(self._heap, (arrive + i * airtime, self._counter, direction, data))

    def _send_due(self, now: float) -> float | None:
        while self._heap and self._heap[0][0] <= now:
            _t, _n, direction, data = heapq.heappop(self._heap)
            out_side = 1 if direction == UP else 0
            peer = self._peers[out_side]
            if peer is None:
                self.stats.of(direction).no_peer += 1
                continue
            self.stats.of(direction).delivered += 1
            # a peer that is not listening (ECONNREFUSED etc.): the radio cannot tell either
            with contextlib.suppress(OSError):
                self._socks[out_side].sendto(data, peer)
        return self._heap[0][0] - now if self._heap else None

    def _read_side(self, side: int) -> None:
        while True:
            try:
                data, addr = self._socks[side].recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break  # ICMP port unreachable from a departed peer
            if not self._fixed[side]:
                self._peers[side] = addr
            self._schedule(UP if side == 0 else DOWN, data, time.monotonic())


def _hostport(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if host not in ("127.0.0.1", "localhost"):
        raise argparse.ArgumentTypeError("peers must be on 127.0.0.1")
    return HOST, int(port)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description="Emulated telemetry radio between a ground station and the robot (UDP, 127.0.0.1). "
                    "Example: robot on udpin:127.0.0.1:14555, ground station on udpout:127.0.0.1:14550: "
                    "python -m ground_station.lab.rigs.link_emulator --gcs-port 14550 --robot-peer 127.0.0.1:14555 --loss 0.05")
    p.add_argument("--gcs-port", type=int, default=14550, help="port the ground station talks to (default %(default)s)")
    p.add_argument("--robot-port", type=int, default=0, help="port the robot talks to (default: any free)")
    p.add_argument("--gcs-peer", type=_hostport, help="fixed ground-station address (it listens); default: learnt")
    p.add_argument("--robot-peer", type=_hostport, help="fixed robot address (it listens); default: learnt")
    p.add_argument("--baud", type=int, default=57600, help="radio baud rate, 8N1 (default %(default)s)")
    p.add_argument("--latency-ms", type=float, default=0.0, help="one-way latency (default %(default)s)")
    p.add_argument("--loss", type=float, default=0.0, help="frame loss probability 0..1 per direction")
    p.add_argument("--duplicate", type=float, default=0.0, help="frame duplication probability 0..1")
    p.add_argument("--reorder", type=float, default=0.0, help="probability a frame is delayed past later ones")
    p.add_argument("--reorder-delay-ms", type=float, default=50.0, help="extra delay of a reordered frame")
    p.add_argument("--queue-bytes", type=int, default=0, help="radio buffer per direction (0 = unbounded)")
    p.add_argument("--seed", type=int, default=0, help="RNG seed (default %(default)s)")
    args = p.parse_args(argv)
    cfg = LinkConfig(baud=args.baud, latency_s=args.latency_ms / 1000, loss=args.loss, duplicate=args.duplicate,
                     reorder=args.reorder, reorder_delay_s=args.reorder_delay_ms / 1000,
                     queue_bytes=args.queue_bytes, seed=args.seed)
    try:
        link = LinkEmulator(cfg, gcs_port=args.gcs_port, robot_port=args.robot_port,
                            gcs_peer=args.gcs_peer, robot_peer=args.robot_peer)
    except (ValueError, OSError) as exc:
        print(f"link_emulator: error: {exc}", file=sys.stderr)
        return 2
    print(f"link_emulator: ground station <-> 127.0.0.1:{link.gcs_port}, robot <-> 127.0.0.1:{link.robot_port}, "
          f"{cfg.bytes_per_s:.0f} B/s each way", flush=True)
    with link:
        try:
            while True:
                time.sleep(5)
                print(f"up {link.stats.up}\ndown {link.stats.down}", flush=True)
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
