"""Child processes and loopback ports, for whatever starts other programs.

Owns the helpers every launcher needs: a port on 127.0.0.1 that was free a
moment ago, stopping a child for sure (a signal, a grace period, then SIGKILL),
and a child that does not outlive its starter (`die_with_parent_code`).
Stdlib only: the tests of every package import it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import signal
import socket
import subprocess
import tempfile
import threading
import time
from pathlib import Path

PORT_HOLD_S = 120.0  # a port handed out here is not handed out again for this long, by any process
PORTS_DIR = Path(tempfile.gettempdir()) / "qnav-ports"  # a file per port handed out, its mtime: when


def free_port(kind: socket.SocketKind = socket.SOCK_STREAM, host: str = "127.0.0.1") -> int:
    """A TCP (or, with kind=SOCK_DGRAM, UDP) port that was free a moment ago on `host`, and not handed
    out by this function in any process on the machine in the last PORT_HOLD_S: the kernel may offer a
    port again once it is closed, and two launchers given the same port would both bind it without an
    error (pymavlink's udpin sets SO_REUSEADDR, with which a second UDP socket takes the port's
    datagrams and the first hears nothing: a robot that never answers, beside other tests)."""
    port = 0
    for _ in range(50):
        with socket.socket(socket.AF_INET, kind) as s:
            s.bind((host, 0))
            port = s.getsockname()[1]
        if _reserve(port):
            break
    return port  # (50 offers all held: the last, the kernel's choice)


def _reserve(port: int, now: float | None = None) -> bool:
    """Mark `port` handed out (PORTS_DIR/<port>) unless it was within PORT_HOLD_S; True if taken. Where
    the marks cannot be kept (no shared temp directory) every port is taken: the kernel's choice."""
    now = time.time() if now is None else now
    try:
        PORTS_DIR.mkdir(exist_ok=True)
        with open(PORTS_DIR / ".lock", "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # released on close
            mark = PORTS_DIR / str(port)
            with contextlib.suppress(FileNotFoundError):
                if now - mark.stat().st_mtime < PORT_HOLD_S:
                    return False
            mark.touch()
            os.utime(mark, (now, now))
            return True
    except OSError:
        return True


def free_udp_port(host: str = "127.0.0.1") -> int:
    """A UDP port that was free a moment ago on `host` (MAVLink links)."""
    return free_port(socket.SOCK_DGRAM, host)


Process = subprocess.Popen[bytes] | subprocess.Popen[str]


def stop_process(proc: Process, timeout_s: float = 5.0, sig: int = signal.SIGTERM, *,
                 group: bool = False) -> int:
    """Send `sig` if `proc` still runs, wait up to timeout_s, then SIGKILL; the exit code.
    `group`: signal the process group of a child started with start_new_session=True."""
    if proc.poll() is None:
        signal_process(proc, sig, group=group)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            signal_process(proc, signal.SIGKILL, group=group)
            proc.wait()
    return proc.returncode


def signal_process(proc: Process, sig: int, *, group: bool = False) -> None:
    """`sig` to `proc` (or to its process group); nothing if it is already gone."""
    if not group:
        proc.send_signal(sig)
        return
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, sig)


def die_with_parent_code() -> str:
    """Python source for the start of a child's `-c`: the child gets SIGTERM when the process
    starting it dies (Linux prctl PR_SET_PDEATHSIG), and exits at once if that is already gone.
    Children in their own session are otherwise orphaned when the starter is killed. "" off the
    main thread: the signal follows the starting *thread*, and a pool thread ends while its
    children should run on."""
    if threading.current_thread() is not threading.main_thread():
        return ""
    return ("import ctypes, os, signal\n"
            "try:\n    ctypes.CDLL(None).prctl(1, signal.SIGTERM)\nexcept (OSError, AttributeError):\n    pass\n"
            f"if os.getppid() != {os.getpid()}:\n    os._exit(1)\n")
