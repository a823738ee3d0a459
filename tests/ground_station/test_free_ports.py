"""ground_station.subprocs.free_port: a port handed out is not handed out again for PORT_HOLD_S by any
process here. Why it matters: on Linux two UDP sockets that set SO_REUSEADDR (pymavlink's udpin does)
bind the same port without an error and the later one takes its datagrams."""

from __future__ import annotations

import socket
import subprocess
import sys
import time

from ground_station import subprocs


def test_two_reuseaddr_udp_sockets_share_a_port_and_the_first_hears_nothing() -> None:
    # the hazard itself, on this kernel: what a port handed out twice does to a robot's udpin
    first, second = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
    with first, second, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        for s in (first, second):
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.settimeout(0.3)
        first.bind(("127.0.0.1", 0))
        port = first.getsockname()[1]
        second.bind(("127.0.0.1", port))  # no error
        sender.sendto(b"hello", ("127.0.0.1", port))
        assert second.recv(16) == b"hello"


def test_a_port_handed_out_is_held_then_free_again(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(subprocs, "PORTS_DIR", tmp_path / "ports")
    now = time.time()
    assert subprocs._reserve(40001, now)
    assert not subprocs._reserve(40001, now + 1.0)  # held: another launcher asked a second later
    assert subprocs._reserve(40002, now + 1.0)
    assert subprocs._reserve(40001, now + subprocs.PORT_HOLD_S + 1.0)  # stale: handed out again
    assert not subprocs._reserve(40001, now + subprocs.PORT_HOLD_S + 2.0)
    monkeypatch.setattr(subprocs, "PORTS_DIR", tmp_path / "no" / "such" / "dir")  # marks cannot be kept
    assert subprocs._reserve(40003, now) and subprocs._reserve(40003, now)


def test_processes_asking_at_once_never_get_the_same_port(tmp_path) -> None:
    code = ("import sys; from ground_station import subprocs as s; from pathlib import Path; "
            "s.PORTS_DIR = Path(sys.argv[1]); "
            "print(' '.join(str(s.free_udp_port() if i % 2 else s.free_port()) for i in range(150)))")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "ports")], stdout=subprocess.PIPE,
                              text=True) for _ in range(4)]
    got = [int(p) for proc in procs for p in proc.communicate(timeout=60)[0].split()]
    assert all(proc.returncode == 0 for proc in procs)
    assert len(got) == 600 and len(set(got)) == 600  # UDP and TCP from one pool: no port twice
    assert len(list((tmp_path / "ports").glob("[0-9]*"))) == 600
