"""`qnav policy revert` (issue 44 item 6, docs/deploy.md "Update a policy"): against a running
qnav-robot (python-can virtual bus, MAVLink over UDP loopback on a free port, a storage folder):
upload A, upload B, revert -> A runs again (the robot's POLICY_ID_HI/LO and its active.qtab), revert
again -> B; a robot without a last good policy refuses in one line (exit 3); no robot: exit 4."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from firmware_py.policy import load_policy
from firmware_py.shipped_policies import resolve_policy_spec
from ground_station.subprocs import free_udp_port, stop_process

BIN = Path(sys.executable).parent


def _robot(storage: Path, port: int) -> subprocess.Popen:
    return subprocess.Popen([BIN / "qnav-robot", "--can", f"virtual:revert-{port}", "--storage", storage,
                             "--policy", "policies:sector", "--mavlink", f"udpout:127.0.0.1:{port}", "-q"],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _qnav(*argv) -> subprocess.CompletedProcess:
    return subprocess.run([BIN / "qnav", *map(str, argv)], capture_output=True, text=True, timeout=120)


def _running_id(url: str) -> str:
    got = _qnav("param", "get", "POLICY_ID", "--mavlink", url, "--no-tlog")
    assert got.returncode == 0, got.stderr
    return got.stdout.split()[-1]  # exact, in hex, from POLICY_ID_HI/LO


def test_revert_makes_the_last_good_policy_active_again_and_back(tmp_path):
    a, b = (Path(resolve_policy_spec(f"policies:{n}")) for n in ("paper10_cell", "sector_memory"))
    id_a, id_b = (f"0x{load_policy(p).policy_id:08x}" for p in (a, b))
    assert id_a != id_b
    storage, port = tmp_path / "robot", free_udp_port()
    url = f"udpin:127.0.0.1:{port}"
    active = storage / "policies" / "active.qtab"
    robot = _robot(storage, port)
    try:
        # one policy activated, none before it in storage: nothing to go back to
        up = _qnav("upload", a, "--activate", "--mavlink", url, "--no-tlog")
        assert up.returncode == 0, up.stderr
        none = _qnav("policy", "revert", "--mavlink", url, "--no-tlog")
        assert none.returncode == 3, none.stderr
        assert none.stderr.strip().splitlines() == [
            "qnav policy revert: error: the robot has no /policies/last_good.qtab: no earlier policy to go back "
            "to (it keeps one once a second policy has been activated)"]
        up = _qnav("upload", b, "--activate", "--mavlink", url, "--no-tlog")
        assert up.returncode == 0, up.stderr
        assert _running_id(url) == id_b and active.read_bytes() == b.read_bytes()

        back = _qnav("policy", "revert", "--mavlink", url, "--no-tlog")
        assert back.returncode == 0, back.stderr
        lines = back.stdout.splitlines()
        assert lines[0] == f"before: the robot runs policy {id_b}; /policies/last_good.qtab holds {id_a}", lines
        assert lines[1].startswith(f"after: the robot runs policy {id_a} (policy CRC 0x"), lines
        assert "confirmed by POLICY_ID/POLICY_CRC params + active.qtab CRC32" in lines[1]
        assert _running_id(url) == id_a
        assert active.read_bytes() == a.read_bytes()
        assert (storage / "policies" / "last_good.qtab").read_bytes() == b.read_bytes()
        assert not (storage / "policies" / "revert.qtab").exists()  # renamed onto active.qtab

        forward = _qnav("policy", "revert", "--mavlink", url, "--no-tlog")  # and forward again
        assert forward.returncode == 0, forward.stderr
        assert forward.stdout.splitlines()[0] == \
            f"before: the robot runs policy {id_a}; /policies/last_good.qtab holds {id_b}"
        assert _running_id(url) == id_b and active.read_bytes() == b.read_bytes()
    finally:
        stop_process(robot)
    log = (storage / "logs" / "robot.log").read_text()  # the robot's own account: upload, upload, revert, revert
    activated = re.findall(r"qnav\.controller .* policy (0x[0-9a-f]{8}) \S+ active", log)
    assert activated[-4:] == [id_a, id_b, id_a, id_b], log[-2000:]


def test_revert_without_a_robot_exits_4_in_one_line():
    got = _qnav("policy", "revert", "--mavlink", f"udpin:127.0.0.1:{free_udp_port()}", "--timeout", "1",
                "--no-tlog")
    assert got.returncode == 4, got.stderr
    errors = [ln for ln in got.stderr.splitlines() if "error" in ln]
    assert len(errors) == 1 and errors[0].startswith("qnav policy revert: error: "), got.stderr
