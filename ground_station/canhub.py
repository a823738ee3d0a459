"""A python-can-remote hub on 127.0.0.1 for a multi-process run (HIL, sitl, demo, benches).

`CanHub` starts `python -m can_remote` on a free port, waits until it accepts
connections and stops it on exit. python-can's `virtual` bus only reaches
buses of the same process, so separate processes (sim and controller) meet on
such a hub; each opens it with `firmware_py.canbus.open_bus(hub.spec)`.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from types import TracebackType

from ground_station.subprocs import die_with_parent_code, exit_code, free_port, stop_process


class CanHub:
    """A python-can-remote hub on 127.0.0.1 for one run (a context manager)."""

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
        args = ["-i", "virtual", "-c", self.channel, "-H", self.host, "-p", str(self.port)]
        # `python -m can_remote ARGS`, gone with its owner (subprocs.die_with_parent_code)
        cmd = [sys.executable, "-c", die_with_parent_code() + "import runpy, sys\n"
               "runpy.run_module('can_remote', run_name='__main__', alter_sys=True)\n", *args]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        # its own session: a Ctrl-C typed in the owner's terminal must not kill the bus before its
        # clients have stopped (the owner stops it last)
        self._proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL, env=env, start_new_session=True)
        deadline = time.monotonic() + self.start_timeout_s
        while time.monotonic() < deadline:
            if exit_code(self._proc) is not None:  # port taken meanwhile, or can_remote broken
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
        return self._proc is not None and exit_code(self._proc) is None

    def __enter__(self) -> CanHub:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()
