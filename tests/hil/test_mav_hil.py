"""The paper's tour over MAVLink, hardware in the loop, across processes:
python-can-remote hub + `qnav-sim` (pymunk, lockstep) + `qnav-robot` with its
MAVLink node (udpout), commanded by `qnav mission upload --targets A,B,C,D`,
`qnav arm` and MISSION_START; MISSION_ITEM_REACHED must arrive for each."""

from __future__ import annotations

import contextlib
import io
import subprocess
import sys
import time
from pathlib import Path

import pytest

from firmware_py.canbus import CanHub
from firmware_py.subprocs import free_udp_port, stop_process
from ground_station import cli
from ground_station.mavlink.link import Link

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


def qnav(*argv: str) -> tuple[int, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(list(argv))
    return code, err.getvalue() + out.getvalue()


@pytest.mark.slow
def test_mission_a_b_c_d_over_mavlink_in_the_sim(tmp_path):
    port = free_udp_port()
    url = f"udpin:127.0.0.1:{port}"
    procs = []
    with CanHub("mavhil") as hub:
        try:
            procs.append(subprocess.Popen(
                [BIN / "qnav-sim", "--map", "paper10", "--can", hub.spec, "--lockstep", "--duration", "3000",
                 "--start", "0.25,0.25,0", "-q"],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT))
            procs.append(subprocess.Popen(
                [BIN / "qnav-robot", "--can", hub.spec, "--lockstep", "--policy", "policies/paper10_cell.qtab",
                 "--start", "0.25,0.25,0", "--storage", tmp_path / "storage", "--duration", "2999.95",
                 "--mavlink", f"udpout:127.0.0.1:{port}", "-q"],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT))
            common = ["--mavlink", url, "--no-tlog", "--timeout", "20"]
            code, out = qnav("mission", "upload", "--targets", "A,B,C,D", *common)
            assert code == 0, out
            with Link(url, tlog=tmp_path / "hil.tlog") as link:
                link.connect(10)
                deadline = time.monotonic() + 30
                while True:  # arming waits for fresh sensor frames from the sim
                    code, out = qnav("arm", *common)
                    if code == 0 or time.monotonic() > deadline:
                        break
                    time.sleep(0.5)
                assert code == 0, out
                link.command(link.m.MAV_CMD_MISSION_START)
                reached, texts = [], []
                deadline = time.monotonic() + 60
                while len(reached) < 4 and time.monotonic() < deadline:
                    msg = link.recv(["MISSION_ITEM_REACHED", "STATUSTEXT"], 1.0)
                    if msg is None:
                        continue
                    if msg.get_type() == "STATUSTEXT":
                        texts.append(msg.text)
                    else:
                        reached.append(msg.seq)
                assert reached == [0, 1, 2, 3], texts
                hb = link.recv("HEARTBEAT", 3.0)
                assert hb is not None and hb.base_mode & link.m.MAV_MODE_FLAG_SAFETY_ARMED
        finally:
            for p in procs:
                stop_process(p, timeout_s=10)
