"""A program on a pseudo-terminal of its own, as an operator's shell runs it, and whether this host's
pseudo-terminals turn a typed Ctrl-C into SIGINT at all.

`ctrl_c_delivery()` answers the second by typing ^C at a plain Python child that only waits for
SIGINT: a sandbox whose terminal layer does not signal the foreground group (CI twice saw `qnav sitl`
on a pty run on for 90 s after ^C, with the same code that passed there before) is then named in the
test's output, and the test sends SIGINT to the terminal's foreground process group itself, which is
what the line discipline would have done. `signal_state(pid)` is what the kernel says of a process's
signals (pending, blocked, ignored, caught), for a report when a process did not react.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import os
import select
import subprocess
import sys
import termios
import time
from collections.abc import Sequence
from pathlib import Path


def _controlling_tty() -> None:  # preexec_fn: the child leads a new session whose terminal is the pty
    os.setsid()
    fcntl.ioctl(0, termios.TIOCSCTTY, 0)


class PtySession:
    """`argv` as the leader of a new session on a fresh pty (stdin, stdout, stderr); `read` collects
    what it prints, `type_ctrl_c` types the terminal's interrupt character."""

    def __init__(self, argv: Sequence[str], *, cwd: Path | None = None, env: dict[str, str] | None = None) -> None:
        self.master, slave = os.openpty()
        try:
            self.proc = subprocess.Popen(list(argv), stdin=slave, stdout=slave, stderr=slave, cwd=cwd, env=env,
                                         preexec_fn=_controlling_tty)
        finally:
            os.close(slave)
        self.output = b""

    def read(self, timeout_s: float) -> bool:
        """Read what is there within timeout_s; False once the terminal is closed (the session ended)."""
        try:
            if select.select([self.master], [], [], timeout_s)[0]:
                self.output += os.read(self.master, 65536)
        except OSError:  # EIO: every process holding the slave has gone
            return False
        return True

    def read_until(self, marker: bytes | None, timeout_s: float) -> bool:
        """Read until `marker` is in the output (None: for the whole timeout); whether it is."""
        deadline = time.monotonic() + timeout_s
        while (marker is None or marker not in self.output) and time.monotonic() < deadline:
            if not self.read(0.2):
                break
        return marker is not None and marker in self.output

    def read_for(self, seconds: float) -> None:
        """Keep reading for `seconds` (or until the terminal closes): what it prints meanwhile is kept."""
        self.read_until(None, seconds)

    def text(self) -> str:
        return self.output.decode(errors="replace")

    def type_ctrl_c(self) -> None:
        os.write(self.master, termios.tcgetattr(self.master)[6][termios.VINTR])

    def foreground_group(self) -> int | None:
        with contextlib.suppress(OSError):
            return os.tcgetpgrp(self.master)
        return None

    def isig(self) -> bool:
        """Whether the terminal turns its interrupt character into a signal (termios ISIG)."""
        return bool(termios.tcgetattr(self.master)[3] & termios.ISIG)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        with contextlib.suppress(OSError):
            os.close(self.master)

    def __enter__(self) -> PtySession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_WAITS_FOR_SIGINT = ("import signal, sys, time\n"
                     "signal.signal(signal.SIGINT, lambda s, f: (print('got SIGINT', flush=True), sys.exit(0)))\n"
                     "print('ready', flush=True)\n"
                     "time.sleep(20)\n")


@functools.cache
def ctrl_c_delivery() -> str | None:
    """None when ^C typed on a pty reaches its foreground group as SIGINT on this host, else what
    happened instead (one line)."""
    with PtySession([sys.executable, "-c", _WAITS_FOR_SIGINT]) as term:
        if not term.read_until(b"ready", 20.0):
            return f"the probe never started on its pty: {term.text()[-200:]!r}"
        fg, leader, isig = term.foreground_group(), term.proc.pid, term.isig()
        term.type_ctrl_c()
        if term.read_until(b"got SIGINT", 5.0):
            return None
        return (f"^C typed on a pty did not reach its foreground group as SIGINT within 5 s (ISIG "
                f"{'on' if isig else 'off'}, foreground group {fg}, session leader {leader}; "
                f"{signal_state(leader)}; printed {term.text()[-120:]!r})")


def signal_state(pid: int) -> str:
    """The kernel's signal masks of `pid` (/proc/PID/status: pending, shared pending, blocked,
    ignored, caught) on one line; bit 2 (0x2) is SIGINT, bit 15 (0x4000) SIGTERM."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError as exc:
        return f"pid {pid}: {exc.strerror or exc}"
    keep = ("State", "SigPnd", "ShdPnd", "SigBlk", "SigIgn", "SigCgt")
    fields = [line.replace("\t", " ") for line in lines if line.split(":")[0] in keep]
    return f"pid {pid} " + ", ".join(fields)
