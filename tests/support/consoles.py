"""Child processes driven through their console: stdout read line by line on
a thread, `expect` waits for a line matching a pattern. Used for MAVProxy
(scripted on stdin) and `qnav sitl` (its printed connection strings)."""

from __future__ import annotations

import os
import queue
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

MAVPROXY = Path(sys.executable).parent / "mavproxy.py"


class ConsoleProcess:
    """`argv` with stdout+stderr read line by line; `expect` fails with the
    last lines of output when the pattern does not come in time or the
    process ends first."""

    what = "the process"

    def __init__(self, argv: list[str], *, cwd: Path, env: dict[str, str], stdin: int | None = subprocess.PIPE,
                 new_session: bool = False) -> None:
        self.proc = subprocess.Popen(argv, stdin=stdin, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, env=env, cwd=cwd, start_new_session=new_session)
        self.lines: queue.Queue[str] = queue.Queue()
        self.log: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))

    def expect(self, pattern: str, timeout_s: float = 20.0) -> str:
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.2)
            except queue.Empty:
                if self.proc.poll() is not None and self.lines.empty():
                    break
                continue
            self.log.append(line)
            if rx.search(line):
                return line
        raise AssertionError(f"{self.what} never printed /{pattern}/; output:\n" + "\n".join(self.log[-40:]))

    def drain(self) -> None:
        """Move what the reader has queued into `log` (after the process ended)."""
        time.sleep(0.3)  # let the reader thread take the last lines
        while not self.lines.empty():
            self.log.append(self.lines.get())


class MavProxy(ConsoleProcess):
    """Stock MAVProxy on `master`, commands on its stdin."""

    what = "MAVProxy"

    def __init__(self, master: str, workdir: Path, modules: str = "param,wp,mode,arm,cmdlong,ftp") -> None:
        super().__init__([sys.executable, str(MAVPROXY), f"--master={master}", f"--state-basedir={workdir}",
                          f"--default-modules={modules}"],
                         cwd=workdir, env=dict(os.environ, PYTHONUNBUFFERED="1"))

    def send(self, cmd: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(cmd + "\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.send("exit")
                self.proc.wait(timeout=5)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(timeout=5)
