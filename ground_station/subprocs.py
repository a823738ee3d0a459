"""Child processes and loopback ports, for whatever starts other programs.

Owns the helpers every launcher needs: a port on 127.0.0.1 that was free a
moment ago, stopping a child for sure (a signal, a grace period, then SIGKILL),
and a child that does not outlive its starter (`die_with_parent_code`).
Stdlib only: the tests of every package import it.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import threading


def free_port(kind: socket.SocketKind = socket.SOCK_STREAM, host: str = "127.0.0.1") -> int:
    """A TCP (or, with kind=SOCK_DGRAM, UDP) port that was free a moment ago on `host`."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind((host, 0))
        port: int = s.getsockname()[1]
        return port


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
