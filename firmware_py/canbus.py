"""Opening the robot's CAN bus from one `--can` spec, and a hub for multi-process runs.

`open_bus(spec)` is the one place a `--can` value becomes a python-can bus:

    virtual:NAME                  python-can's in-process virtual bus
    remote:ws://127.0.0.1:PORT/   a python-can-remote hub (across processes; HIL runs
                                  only, so python-can-remote is the `qnav[hil]` extra)
    socketcan:CHANNEL             Linux SocketCAN (vcan0, can0)
    slcan:DEVICE                  serial-line CAN adapter (DEVICE[@BAUD])
    None or ""                    python-can's own configuration (CAN_INTERFACE,
                                  CAN_CHANNEL, ~/.canrc), resolved by python-can

`CanHub` starts a python-can-remote hub on 127.0.0.1 on a free port, waits
until it accepts connections and stops it on exit. python-can's `virtual`
bus only reaches buses of the same process, so separate processes (sim and
controller) meet on such a hub. Stdlib and python-can only.
"""

from __future__ import annotations

import importlib.util
import os
import socket
import subprocess
import sys
import time
from types import TracebackType
from typing import Any

import can

from firmware_py.subprocs import free_port, stop_process

SPEC_FORMS = ("virtual:NAME", "remote:ws://127.0.0.1:PORT/", "socketcan:CHANNEL", "slcan:DEVICE")


class CanSpecError(ValueError):
    """A `--can` value that cannot be turned into a bus; the text is one line."""


def parse_spec(spec: str | None) -> dict[str, Any]:
    """python-can keyword arguments for `spec` ({} means python-can's own config)."""
    if spec is None or spec.strip() == "":
        return {}
    interface, sep, channel = spec.partition(":")
    if not sep or not channel:
        raise CanSpecError(f"bad --can {spec!r}: expected one of {', '.join(SPEC_FORMS)}")
    if interface == "virtual":
        return {"interface": "virtual", "channel": channel}
    if interface == "remote":
        if not channel.startswith(("ws://", "wss://")):
            raise CanSpecError(f"bad --can {spec!r}: remote needs a ws:// URL, e.g. remote:ws://127.0.0.1:54701/")
        return {"interface": "remote", "channel": channel}
    if interface == "socketcan":
        return {"interface": "socketcan", "channel": channel}
    if interface == "slcan":
        return {"interface": "slcan", "channel": channel}
    raise CanSpecError(f"bad --can {spec!r}: unknown interface {interface!r} "
                       f"(expected virtual, remote, socketcan or slcan)")


def _installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def open_bus(spec: str | None, **kwargs: Any) -> can.BusABC:
    """Open the bus named by `spec` (see the module docstring); extra kwargs go to python-can."""
    config = parse_spec(spec)
    if config.get("interface") == "remote" and not _installed("can_remote"):
        raise CanSpecError(f"--can {spec}: the HIL hub transport needs python-can-remote: "
                           "pip install 'qnav[hil]'")
    config.update(kwargs)
    try:
        return can.Bus(**config)
    except (can.CanError, OSError, ValueError, ImportError, TypeError) as exc:
        where = spec or "python-can default configuration"
        detail = " ".join(str(exc).split()) or type(exc).__name__
        raise CanSpecError(f"cannot open CAN bus {where!r}: {detail}") from None


class CanHub:
    """A python-can-remote hub on 127.0.0.1 for one run (a context manager).

    >>> with CanHub("qnav") as hub:
    ...     bus = open_bus(hub.spec)
    """

    def __init__(self, channel: str = "qnav", port: int | None = None,
                 start_timeout_s: float = 15.0) -> None:
        self.channel = channel
        self.host = "127.0.0.1"
        self.port = port
        self.start_timeout_s = start_timeout_s
        self._proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}/"

    @property
    def spec(self) -> str:
        """The `--can` value that reaches this hub."""
        return f"remote:{self.url}"

    def start(self) -> CanHub:
        fixed = self.port is not None
        for _attempt in range(1 if fixed else 3):
            if not fixed:
                self.port = free_port(host=self.host)
            if self._launch():
                return self
        raise RuntimeError(f"python-can-remote hub did not start on {self.host}:{self.port}")

    def _launch(self) -> bool:
        cmd = [sys.executable, "-m", "can_remote", "-i", "virtual", "-c", self.channel,
               "-H", self.host, "-p", str(self.port)]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        # its own session: a Ctrl-C typed in the owner's terminal goes to the terminal's whole
        # process group and must not kill the bus before its clients have stopped (the owner
        # stops it last, stop())
        self._proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL, env=env, start_new_session=True)
        deadline = time.monotonic() + self.start_timeout_s
        while time.monotonic() < deadline:
            if self._proc.poll() is not None:  # port taken meanwhile, or can_remote broken
                self._proc = None
                return False
            try:
                with socket.create_connection((self.host, self.port), timeout=0.2):
                    return True
            except OSError:
                time.sleep(0.05)
        self.stop()
        return False

    def stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            stop_process(proc)

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def __enter__(self) -> CanHub:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
