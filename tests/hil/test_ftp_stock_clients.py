"""The robot's FTP shell against stock clients over UDP loopback: pymavlink's
`python -m pymavlink.mavftp` (put/get/crc/list/rename/rm), MAVProxy's
`ftp put`/`ftp get`, path-escape attempts, and kill -9 in the middle of an
upload. Every process started here is stopped here."""

import os
import random
import subprocess
import sys
import time
from pathlib import Path

import pytest

from firmware_py.storage import ACTIVE_POLICY, Storage, boot_policy_candidates, ftp_crc32
from ground_station.lab.rigs import link_emulator
from ground_station.lab.rigs.ftp_shell import robot_ftp_process
from ground_station.subprocs import free_udp_port, stop_process

pytestmark = pytest.mark.slow
ENV = dict(os.environ, MAVLINK20="1")
REPO = Path(__file__).resolve().parents[2]
MAVPROXY = REPO / ".venv" / "bin" / "mavproxy.py"


def mavftp(port, *args, cwd, timeout=60):
    """One stock pymavlink mavftp command (a short idle time keeps the test quick)."""
    cmd = [sys.executable, "-m", "pymavlink.mavftp", "--device", f"udpin:127.0.0.1:{port}",
           "--idle_detection_time", "1.5", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=ENV, cwd=cwd)


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    """(storage root, client port) of a standalone robot FTP shell sending to the client port."""
    root = tmp_path_factory.mktemp("robot") / "root"
    port = free_udp_port()
    with robot_ftp_process(root, f"udpout:127.0.0.1:{port}"):
        yield root, port


def test_pymavlink_mavftp_put_get_crc_list_rename_rm(robot, tmp_path):
    root, port = robot
    data = random.Random(1).randbytes(30_001)
    (tmp_path / "up.bin").write_bytes(data)
    out = mavftp(port, "put", "up.bin", "/policies/up.bin", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert (root / "policies" / "up.bin").read_bytes() == data

    out = mavftp(port, "get", "/policies/up.bin", "down.bin", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "down.bin").read_bytes() == data

    out = mavftp(port, "crc", "/policies/up.bin", cwd=tmp_path)
    assert out.returncode == 0 and f"0x{ftp_crc32(data):08x}" in out.stderr + out.stdout

    out = mavftp(port, "list", "/policies", cwd=tmp_path)
    assert out.returncode == 0 and "up.bin\t30001" in out.stderr + out.stdout

    out = mavftp(port, "rename", "/policies/up.bin", "/policies/moved.bin", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert (root / "policies" / "moved.bin").read_bytes() == data
    assert not (root / "policies" / "up.bin").exists()

    out = mavftp(port, "rm", "/policies/moved.bin", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert not (root / "policies" / "moved.bin").exists()

    out = mavftp(port, "rm", "/policies/moved.bin", cwd=tmp_path)
    assert out.returncode != 0  # already gone: FileNotFound


def test_stock_client_path_escapes_are_refused(robot, tmp_path):
    root, port = robot
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret").write_bytes(b"secret")
    link = root / "policies" / "evil"
    os.symlink(outside, link)
    try:
        (tmp_path / "x.bin").write_bytes(b"payload")
        before = sorted(p.name for p in root.parent.iterdir())
        for remote in ("../x.bin", "/../../x.bin", "/policies/../../x.bin", "/etc/passwd", "/policies/evil/x.bin"):
            out = mavftp(port, "put", "x.bin", remote, cwd=tmp_path)
            assert out.returncode != 0, remote
        out = mavftp(port, "get", "/etc/passwd", "passwd", cwd=tmp_path)
        assert out.returncode != 0 and not (tmp_path / "passwd").exists()
        out = mavftp(port, "get", "/policies/evil/secret", "secret", cwd=tmp_path)
        assert out.returncode != 0 and not (tmp_path / "secret").exists()
        assert sorted(p.name for p in outside.iterdir()) == ["secret"]
        assert sorted(p.name for p in root.parent.iterdir()) == before
        assert not (root / "etc").exists()
    finally:
        link.unlink()


def _mavproxy(port, command, cwd):
    return subprocess.Popen(
        [sys.executable, str(MAVPROXY), f"--master=udpin:127.0.0.1:{port}", "--no-state", "--non-interactive",
         "--default-modules=ftp", f"--cmd={command}"],
        cwd=cwd, env=ENV, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _wait_for(predicate, timeout_s):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.1)
    return False


def _stop(proc):
    stop_process(proc)
    out = proc.stdout.read()
    proc.stdout.close()
    return out


@pytest.mark.skipif(not MAVPROXY.exists(), reason="MAVProxy is not installed in .venv (pip install -e '.[dev]')")
def test_mavproxy_ftp_put_and_get(robot, tmp_path):
    root, port = robot
    data = random.Random(2).randbytes(12_345)
    (tmp_path / "mp.bin").write_bytes(data)
    target = root / "policies" / "mp.bin"
    proc = _mavproxy(port, "ftp put mp.bin /policies/mp.bin", tmp_path)
    try:
        ok = _wait_for(lambda: target.exists() and target.read_bytes() == data, 40)
    finally:
        log = _stop(proc)
    assert ok, log

    proc = _mavproxy(port, "ftp get /policies/mp.bin back.bin", tmp_path)
    back = tmp_path / "back.bin"
    try:
        ok = _wait_for(lambda: back.exists() and back.read_bytes() == data, 40)
    finally:
        log = _stop(proc)
    assert ok, log


def test_kill_9_mid_upload_leaves_no_partial_file(tmp_path):
    emu = link_emulator
    root = tmp_path / "root"
    store = Storage(root)
    store.write_atomic(ACTIVE_POLICY, b"the good policy")
    data = random.Random(3).randbytes(60_000)  # ~14 s at 57600 baud: plenty of time to kill
    (tmp_path / "big.qtab").write_bytes(data)
    client_port = free_udp_port()
    link = emu.LinkEmulator(emu.LinkConfig(), gcs_peer=("127.0.0.1", client_port))
    with link, robot_ftp_process(root, f"udpout:127.0.0.1:{link.robot_port}") as proc:
        put = subprocess.Popen(
            [sys.executable, "-m", "pymavlink.mavftp", "--device", f"udpin:127.0.0.1:{client_port}",
             "put", "big.qtab", "/policies/big.qtab"],
            cwd=tmp_path, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            temps = lambda: [p for p in (root / "policies").iterdir() if p.name.startswith(".qnav-tmp-")]  # noqa: E731
            assert _wait_for(lambda: temps() and temps()[0].stat().st_size > 5_000, 30)
            proc.kill()  # SIGKILL: no cleanup, no commit
            proc.wait()
            partial = temps()
            assert len(partial) == 1 and 0 < partial[0].stat().st_size < len(data)
            assert not (root / "policies" / "big.qtab").exists()
        finally:
            put.kill()
            put.wait()
    # restart: the temporary file is swept away, the real name never appeared,
    # and boot picks the policy that was active before
    with robot_ftp_process(root, f"udpout:127.0.0.1:{free_udp_port()}"):
        assert _wait_for(lambda: sorted(p.name for p in (root / "policies").iterdir()) == ["active.qtab"], 10)
    assert boot_policy_candidates(Storage(root))[0] == str(root.resolve() / "policies" / "active.qtab")
    assert (root / "policies" / "active.qtab").read_bytes() == b"the good policy"
