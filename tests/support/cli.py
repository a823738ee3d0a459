"""`qnav` run in the test's own process, and an idle `qnav-robot` to point it at."""

from __future__ import annotations

import contextlib
import io
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

from ground_station import cli
from ground_station.subprocs import free_udp_port, stop_process

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


def run_qnav(*argv: str) -> tuple[int, str, str]:
    """`qnav ARGV...` in-process: (exit code, stdout, stderr); an argparse error's exit is its code."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = cli.main(list(argv))
        except SystemExit as exc:  # argparse errors
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


def start_robot(tmp: Path, port: int, *extra: str) -> subprocess.Popen:
    """`qnav-robot` with the shipped paper10 policy on a virtual CAN bus of its own (no sim: its inputs are
    stale, so it refuses to arm), sending MAVLink to UDP `port` on loopback."""
    return subprocess.Popen(
        [BIN / "qnav-robot", "--can", f"virtual:gcs-{port}", "--policy", "policies:paper10_cell",
         "--storage", tmp / f"storage-{port}", "--mavlink", f"udpout:127.0.0.1:{port}", "-q", *extra],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT)


@contextlib.contextmanager
def idle_robot(tmp: Path) -> Iterator[str]:
    """A `start_robot` robot for the block; yields the ground station's connection string."""
    port = free_udp_port()
    proc = start_robot(tmp, port)
    try:
        yield f"udpin:127.0.0.1:{port}"
    finally:
        stop_process(proc, timeout_s=10)
