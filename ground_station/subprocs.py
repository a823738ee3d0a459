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


def exit_code(proc: Process) -> int | None:
    """`proc`'s exit code (negative: the signal that ended it) once it has ended, else None; like
    `Popen.poll()`, but it leaves the child unreaped and never takes Popen's waitpid lock. poll()
    takes that lock and a KeyboardInterrupt raised just after the take (CPython checks for signals
    on returning from the C call, before the try that gives it back) leaves it held: every later
    poll() then says "running" and wait() blocks for good; measured 3 in 2,000 Ctrl-Cs of a loop
    polling a child. A Ctrl-C landing in a launcher's watch loop then hung its clean stop."""
    if proc.returncode is not None:
        return proc.returncode
    try:
        res = os.waitid(os.P_PID, proc.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT)
    except ChildProcessError:  # reaped meanwhile (a wait() in another thread): Popen has the code
        return proc.returncode
    if res is None:
        return None
    return -res.si_status if res.si_code in (os.CLD_KILLED, os.CLD_DUMPED) else res.si_status


def wait_exit(proc: Process, timeout_s: float) -> int | None:
    """`proc`'s exit code once it has ended (None: still running after `timeout_s`), watched with
    `exit_code`, then reaped if Popen's waitpid lock allows; never blocks beyond timeout_s + 1 s."""
    deadline = time.monotonic() + timeout_s
    while (code := exit_code(proc)) is None and time.monotonic() < deadline:
        time.sleep(0.02)
    if code is not None:
        with contextlib.suppress(subprocess.TimeoutExpired):  # the lock held: it stays a zombie until we exit
            proc.wait(timeout=1.0)
    return code


def stop_process(proc: Process, timeout_s: float = 5.0, sig: int = signal.SIGTERM, *,
                 group: bool = False) -> int | None:
    """Send `sig` if `proc` still runs, wait up to timeout_s, then SIGKILL; the exit code (None only
    if it outlived SIGKILL by 10 s). `group`: signal the process group of a child started with
    start_new_session=True."""
    if exit_code(proc) is None:
        signal_process(proc, sig, group=group)
        if wait_exit(proc, timeout_s) is None:
            signal_process(proc, signal.SIGKILL, group=group)
            wait_exit(proc, 10.0)
    return exit_code(proc)


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
