"""systemd's service notifications (sd_notify), stdlib only: READY, a watchdog that only pets while
the control loop ticks, STOPPING.

Under `Type=notify` with `WatchdogSec=` (the shipped unit, docs/deploy.md) systemd sets
NOTIFY_SOCKET and WATCHDOG_USEC. `ServiceNotifier.start(ticks)` sends READY=1 and starts a thread
that sends WATCHDOG=1 every half watchdog interval, but only when `ticks()` (the node's tick count)
has moved since the last time: a control loop that hangs stops the pets, and systemd restarts the
service (`Restart=on-failure`). The control tick itself never touches the socket. Without
NOTIFY_SOCKET (not under systemd) everything here is a no-op.
"""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Callable


class ServiceNotifier:
    def __init__(self, address: str | None, watchdog_us: int | None) -> None:
        self.address = address
        self.watchdog_us = watchdog_us
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        if address:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._sock.setblocking(False)

    @classmethod
    def from_env(cls, env: dict[str, str] | None = None) -> ServiceNotifier:
        env = dict(os.environ) if env is None else env
        addr = env.get("NOTIFY_SOCKET") or None
        if addr and addr.startswith("@"):
            addr = "\0" + addr[1:]  # an abstract socket
        wd = env.get("WATCHDOG_USEC")
        pid = env.get("WATCHDOG_PID")
        watchdog = int(wd) if wd and wd.isdigit() and int(wd) > 0 and (not pid or pid == str(os.getpid())) else None
        return cls(addr, watchdog)

    def notify(self, state: str) -> bool:
        if self._sock is None or self.address is None:
            return False
        try:
            self._sock.sendto(state.encode(), self.address)
        except OSError:
            return False  # systemd gone or busy: never an error for the robot
        return True

    def start(self, ticks: Callable[[], int], status: Callable[[], str] | None = None) -> None:
        self.notify("READY=1")
        if self.watchdog_us is None or self._sock is None:
            return
        half_s = self.watchdog_us / 2e6

        def pet() -> None:
            last = -1
            while not self._stop.wait(half_s):
                now = ticks()
                if now != last:
                    last = now
                    self.notify("WATCHDOG=1" + (f"\nSTATUS={status()}" if status else ""))

        self._thread = threading.Thread(target=pet, name="qnav-sd-watchdog", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        self.notify("STOPPING=1")
        if self._sock is not None:
            self._sock.close()
            self._sock = None
