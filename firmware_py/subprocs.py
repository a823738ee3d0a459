"""Child processes and loopback ports, for whatever starts other programs.

Owns the two helpers every launcher needs (the CAN hub, the benches, the
demo, the tests): a port on 127.0.0.1 that was free a moment ago, and
stopping a child for sure (a signal, a grace period, then SIGKILL).

Stdlib only: firmware_py uses it, and ground_station, sim_bridge and the
tests import it from here.
"""

from __future__ import annotations

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


def stop_process(proc: subprocess.Popen[bytes] | subprocess.Popen[str], timeout_s: float = 5.0,
                 sig: int = signal.SIGTERM) -> int:
    """Send `sig` if `proc` still runs, wait up to timeout_s, then SIGKILL; the exit code."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode
