"""`qnav upload` end to end: pymavlink's MAVFTP client -> emulated lossy radio
-> the robot's FTP shell (own process, policy-loader activation hook)."""

import os
import random
import subprocess
import sys
from array import array

import pytest

from firmware_py.kinds.cell.encoder import CellEncoder
from firmware_py.policy import dump_policy, load_policy
from ground_station.lab.rigs import link_emulator as emu
from ground_station.lab.rigs.ftp_shell import robot_ftp_process
from ground_station.subprocs import free_udp_port

pytestmark = pytest.mark.slow
ENV = dict(os.environ, MAVLINK20="1")


def make_policy(seed: int) -> bytes:
    rnd = random.Random(seed)
    enc = CellEncoder(10, 10, 2)
    table = array("b", [rnd.randint(-127, 127) for _ in range(enc.n_states * enc.n_actions)])
    return dump_policy(enc, table, "int8", 0.1, goals=[(1, 1), (8, 8)], metadata={"seed": seed})


def qnav_upload(*args, timeout=120):
    # --no-tlog: the session log (tested in test_mav_link.py) would land in the checkout's runs/
    return subprocess.run([sys.executable, "-m", "ground_station.cli", "upload", "--no-tlog", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, env=ENV)


@pytest.fixture
def lossy_robot(tmp_path):
    """(root, url): robot FTP shell behind a radio losing 5 % of frames, with
    duplicates and reordering."""
    root = tmp_path / "root"
    robot_port = free_udp_port()
    cfg = emu.LinkConfig(loss=0.05, duplicate=0.02, reorder=0.02, seed=11)
    with robot_ftp_process(root, f"udpin:127.0.0.1:{robot_port}"), \
            emu.LinkEmulator(cfg, robot_peer=("127.0.0.1", robot_port)) as link:
        yield root, f"udpout:127.0.0.1:{link.gcs_port}"


def test_upload_activate_keeps_last_good_and_refuses_corrupt_files(lossy_robot, tmp_path):
    root, url = lossy_robot
    first, second = tmp_path / "first.qtab", tmp_path / "second.qtab"
    first.write_bytes(make_policy(1))
    second.write_bytes(make_policy(2))

    out = qnav_upload(first, "--activate", "--mavlink", url)
    assert out.returncode == 0, out.stdout + out.stderr
    pid = load_policy(first).policy_id
    assert f"policy id 0x{pid:08x}" in out.stdout and "verified" in out.stdout
    assert (root / "policies" / "active.qtab").read_bytes() == first.read_bytes()

    out = qnav_upload(second, "--activate", "--mavlink", url)
    assert out.returncode == 0, out.stdout + out.stderr
    assert (root / "policies" / "active.qtab").read_bytes() == second.read_bytes()
    assert (root / "policies" / "last_good.qtab").read_bytes() == first.read_bytes()

    bad = bytearray(second.read_bytes())
    bad[200] ^= 0xFF  # inside the table: the file CRC no longer matches
    corrupt = tmp_path / "corrupt.qtab"
    corrupt.write_bytes(bytes(bad))
    out = qnav_upload(corrupt, "--activate", "--mavlink", url)  # refused here, before anything is sent (issue 46)
    assert out.returncode == 2 and "CRC32 mismatch" in out.stderr, out.stdout + out.stderr
    assert not (root / "policies" / "corrupt.qtab").exists()
    out = qnav_upload(corrupt, "--activate", "--force", "--mavlink", url)  # the robot's own refusal
    assert out.returncode == 3, out.stdout + out.stderr
    assert "refused" in out.stderr and "crc" in out.stderr.lower() and "refused" not in out.stdout
    assert (root / "policies" / "active.qtab").read_bytes() == second.read_bytes()
    assert (root / "policies" / "last_good.qtab").read_bytes() == first.read_bytes()
    assert (root / "policies" / "corrupt.qtab").read_bytes() == bytes(bad)  # uploaded, not activated


def test_signed_upload(tmp_path):
    key = tmp_path / "key"
    key.write_text("correct horse battery staple\n")  # a passphrase, as MAVProxy's signing setup
    policy = tmp_path / "p.qtab"
    policy.write_bytes(make_policy(3))
    root = tmp_path / "root"
    port = free_udp_port()
    with robot_ftp_process(root, f"udpin:127.0.0.1:{port}", key_file=key):
        out = qnav_upload(policy, "--activate", "--mavlink", f"udpout:127.0.0.1:{port}", "--signing-key", key)
        assert out.returncode == 0, out.stdout + out.stderr
        assert (root / "policies" / "active.qtab").read_bytes() == policy.read_bytes()
        # the robot drops unsigned FTP: an unsigned client gets nowhere
        other = tmp_path / "other.qtab"
        other.write_bytes(make_policy(4))
        out = qnav_upload(other, "--mavlink", f"udpout:127.0.0.1:{port}", "--attempts", "1", "--timeout", "5")
        assert out.returncode == 4 and "does not answer" in out.stderr, out.stdout + out.stderr
        assert not (root / "policies" / "other.qtab").exists()


def test_clear_errors(tmp_path):
    out = qnav_upload(tmp_path / "missing.qtab", "--mavlink", "udpout:127.0.0.1:9")
    assert out.returncode == 2 and "no such file" in out.stderr
    f = tmp_path / "p.qtab"
    f.write_bytes(make_policy(5))
    out = qnav_upload(f, "--mavlink", f"udpout:127.0.0.1:{free_udp_port()}", "--timeout", "2")
    assert out.returncode == 4 and "no HEARTBEAT" in out.stderr and "error" not in out.stdout
    out = qnav_upload(f, "--mavlink", "udpout:127.0.0.1:9", "--signing-key", tmp_path / "nokey")
    assert out.returncode == 2 and "signing key" in out.stderr


def test_upload_takes_a_shipped_policy_by_name(tmp_path):
    """`qnav upload policies:sector`, as the README shows, resolves the shipped file (it once
    failed with "policies:sector: no such file"); an unknown name is a one-line refusal."""
    from firmware_py.shipped_policies import shipped_policy

    root = tmp_path / "root"
    port = free_udp_port()
    with robot_ftp_process(root, f"udpin:127.0.0.1:{port}"):
        out = qnav_upload("policies:sector", "--mavlink", f"udpout:127.0.0.1:{port}")
        assert out.returncode == 0, out.stdout + out.stderr
    assert (root / "policies" / "sector.qtab").read_bytes() == shipped_policy("sector").read_bytes()
    out = qnav_upload("policies:no_such_policy", "--mavlink", "udpout:127.0.0.1:9")
    assert out.returncode == 2 and "no_such_policy" in out.stderr and len(out.stderr.strip().splitlines()) == 1


def test_help():
    out = subprocess.run([sys.executable, "-m", "ground_station.cli", "upload", "--help"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "--activate" in out.stdout and "--signing-key" in out.stdout
    out = subprocess.run([sys.executable, "-m", "ground_station.cli", "bench", "upload", "--help"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "--json" in out.stdout
