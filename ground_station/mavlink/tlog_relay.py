"""A UDP relay in front of a robot's MAVLink that records the session as a .tlog.

`qnav sitl` puts the robot behind it so that the run's own telemetry is recorded whatever ground
station connects (or none): the robot sends to the relay (`robot_url()`: `udpout:127.0.0.1:PORT`,
from the robot's very first frame), and the relay owns the public connection string ground stations
use, with pymavlink's meaning:

* `udpin:HOST:PORT` (the robot listens): ground stations send to
  HOST:PORT; the robot's frames go to the last address that sent, as
  pymavlink's own `udpin` does (the last GCS to send gets the telemetry);
* `udpout:HOST:PORT` (the robot sends, e.g. to QGroundControl's 14550):
  the robot's frames go there, replies come back to the relay's socket.

Every MAVLink frame, both ways, goes into the tlog as the tlog format has it (8-byte big-endian µs
wall time, then the frame as sent; a datagram holding several frames gives several records); a frame
whose header does not parse is relayed but not recorded. Frames are relayed byte for byte
(signatures untouched). `close()` stops the thread and closes the file.
"""

from __future__ import annotations

import contextlib
import select
import socket
import struct
import threading
import time
from pathlib import Path

RELAYED_SCHEMES = ("udpin", "udpout")
FLUSH_S = 1.0


def relayable(url: str) -> bool:
    """A connection string the relay can stand in for (UDP, either way)."""
    return url.partition(":")[0] in RELAYED_SCHEMES


def split_frames(data: bytes) -> list[bytes]:
    """The MAVLink 1/2 frames of one datagram (bytes that are no frame are dropped)."""
    out, i = [], 0
    while i < len(data):
        magic = data[i]
        if magic == 0xFD and i + 3 <= len(data):
            size = 12 + data[i + 1] + (13 if data[i + 2] & 0x01 else 0)
        elif magic == 0xFE and i + 2 <= len(data):
            size = 8 + data[i + 1]
        else:
            i += 1
            continue
        if i + size > len(data):
            break
        out.append(data[i:i + size])
        i += size
    return out


def _addr(rest: str) -> tuple[str, int]:
    host, _, port = rest.rpartition(":")
    return host or "127.0.0.1", int(port)


class TlogRelay:
    """See the module docstring. `public`: the connection string ground stations see."""

    def __init__(self, public: str, tlog: str | Path) -> None:
        scheme, _, rest = public.partition(":")
        if scheme not in RELAYED_SCHEMES:
            raise ValueError(f"{public}: the relay takes udpin:HOST:PORT or udpout:HOST:PORT")
        self.public = public
        self.tlog_path = Path(tlog)
        self._gcs_fixed = scheme == "udpout"
        self._gcs_addr: tuple[str, int] | None = _addr(rest) if self._gcs_fixed else None
        self.gcs_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        if not self._gcs_fixed:
            self.gcs_sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as pymavlink's udpin
            self.gcs_sock.bind(_addr(rest))
        self.robot_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.robot_sock.bind(("127.0.0.1", 0))
        for sock in (self.gcs_sock, self.robot_sock):
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 21)
        self._robot_addr: tuple[str, int] | None = None
        self._file = open(self.tlog_path, "wb")  # noqa: SIM115 - closed in close()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="tlog-relay", daemon=True)
        self._thread.start()

    def robot_url(self) -> str:
        """What the robot is given as its --mavlink: it sends to the relay from its first frame."""
        return f"udpout:127.0.0.1:{self.robot_sock.getsockname()[1]}"

    def _record(self, data: bytes) -> None:
        stamp = struct.pack(">Q", int(time.time() * 1e6) & ~3)
        with self._lock:
            if self._file.closed:
                return
            self._file.write(b"".join(stamp + f for f in split_frames(data)))

    def _run(self) -> None:
        next_flush = time.monotonic() + FLUSH_S
        socks = [self.gcs_sock, self.robot_sock]
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select(socks, [], [], 0.2)
            except (OSError, ValueError):  # closed under us
                return
            for sock in ready:
                try:
                    data, addr = sock.recvfrom(65536)
                except OSError:
                    continue
                self._record(data)
                if sock is self.robot_sock:
                    self._robot_addr = addr
                    dest, out = self._gcs_addr, self.gcs_sock
                else:
                    if not self._gcs_fixed:
                        self._gcs_addr = addr
                    dest, out = self._robot_addr, self.robot_sock
                if dest is None:  # nowhere to go yet (no GCS has sent; the robot not heard)
                    continue
                with contextlib.suppress(OSError):  # nobody listening there (yet): as a UDP link is
                    out.sendto(data, dest)
            if time.monotonic() >= next_flush:
                with self._lock:
                    if not self._file.closed:
                        self._file.flush()
                next_flush = time.monotonic() + FLUSH_S

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for sock in (self.gcs_sock, self.robot_sock):
            sock.close()
        with self._lock:
            self._file.close()
