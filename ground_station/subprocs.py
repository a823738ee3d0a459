"""Child processes and loopback ports, for whatever starts other programs.

Owns the two helpers every launcher needs (the CAN hub, the benches, the
demo, the tests): a port on 127.0.0.1 that was free a moment ago, and
stopping a child for sure (a signal, a grace period, then SIGKILL).

Stdlib only: firmware_py uses it, and ground_station, sim_bridge and the
tests import it from here.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess


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

    `group`: signal the child's whole process group (a child started with
    start_new_session=True leads its own group, pgid == pid)."""
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
