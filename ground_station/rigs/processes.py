"""`qnav-robot` as a child process for the fault scenarios, always stopped.

The robot listens for MAVLink on `udpin:127.0.0.1:PORT` (ground stations and
the link emulator send to it) with its storage in a directory the scenario
owns. Without `can` it gets a private in-process `virtual` bus: no sensors,
so it stays disarmed in STANDBY, which is all uploads, activations and
parameter saves need. Output goes to a log file (a pipe could fill up and
stall the robot).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import uuid
from pathlib import Path

BIN = Path(sys.executable).parent


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# `qnav-robot` with SIGINT restored: a parent started in the background (nohup, `&`) passes
# SIGINT ignored on to its children, and the robot would then never end cleanly on stop().
_MAIN = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
         "from firmware_py.cli import main; sys.exit(main())")


class RobotProcess:
    """See the module docstring. `kill9()` is the crash; `stop()` the clean end."""

    def __init__(self, storage: Path, *, port: int | None = None, key_file: Path | None = None,
                 can: str | None = None, extra: list[str] | None = None, log: Path | None = None) -> None:
        self.storage = Path(storage)
        self.port = port or free_udp_port()
        self.cmd = [sys.executable, "-c", _MAIN, "--can", can or f"virtual:faults-{uuid.uuid4().hex}",
                    "--storage", str(self.storage), "--mavlink", f"udpin:127.0.0.1:{self.port}"]
        if key_file is not None:
            self.cmd += ["--signing-key", str(key_file)]
        self.cmd += extra or []
        self.log = log or self.storage.parent / f"robot-{self.port}.log"
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        """What a ground station connects to (directly, without the emulator)."""
        return f"udpout:127.0.0.1:{self.port}"

    def start(self) -> RobotProcess:
        self.storage.mkdir(parents=True, exist_ok=True)
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(self.cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                                         env=dict(os.environ, MAVLINK20="1", PYTHONUNBUFFERED="1"))
        return self

    @property
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def kill9(self) -> None:
        proc = self.proc
        if proc is not None and proc.poll() is None:  # self.alive
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)

    def stop(self, timeout_s: float = 20.0) -> int | None:
        """SIGINT (clean exit, stats written), then SIGKILL if it hangs (its shutdown joins
        two threads with 5 s timeouts, so allow more than that)."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        return self.proc.returncode

    def log_tail(self, n: int = 5) -> str:
        try:
            return " | ".join(self.log.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""

    def __enter__(self) -> RobotProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
