"""HIL across processes: python-can-remote hub + `qnav-sim` + `qnav-robot`,
each a separate process on 127.0.0.1, lockstep, with a sector policy in an
open arena (the cell policy's goal, e-stop, sensor-stop and mission runs
across processes are tests/hil/test_hil_transports.py's, on the hub and on
vcan0)."""

import subprocess
import sys
from pathlib import Path

from firmware_py.policy import dump_policy
from ground_station.canhub import CanHub
from tests.support.controller_rig import sector_seek_policy

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


def start(cmd):
    return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT)


def finish(*procs, timeout=90):
    outs = []
    try:
        for p in procs:
            outs.append(p.communicate(timeout=timeout))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    return outs


def test_sector_policy_across_processes_in_open_arena(tmp_path):
    (tmp_path / "open.map").write_text("type octile\nheight 6\nwidth 6\nmap\n" + "......\n" * 6)
    pol = sector_seek_policy()
    qtab = tmp_path / "seek.qtab"
    qtab.write_bytes(dump_policy(pol.encoder, pol.table.tolist(), "int8", 0.01, map_geometry=pol.map_geometry))
    with CanHub("hilsec") as hub:
        sim = start([BIN / "qnav-sim", "--map", tmp_path / "open.map", "--can", hub.spec,
                     "--lockstep", "--duration", "30", "--start", "0.75,0.75,180", "-q",
                     "--trajectory", tmp_path / "traj.csv"])
        rob = start([BIN / "qnav-robot", "--can", hub.spec, "--lockstep", "--policy", qtab,
                     "--start", "0.75,0.75,180", "--goal", "2.25,2.25", "--duration", "29.95",
                     "--mavlink", "none"])
        (_, sim_err), (_, rob_err) = finish(sim, rob)
    assert sim.returncode == 0, sim_err
    assert rob.returncode == 0, rob_err
    assert "GOAL_REACHED" in rob_err
    last = (tmp_path / "traj.csv").read_text().strip().splitlines()[-1].split(",")
    x, y = float(last[2]), float(last[3])  # ground truth from the sim
    assert abs(x - 2.25) < 0.2 and abs(y - 2.25) < 0.2
