"""HIL across processes: python-can-remote hub + `qnav-sim` + `qnav-robot`,
each a separate process on 127.0.0.1, lockstep."""

import json
import re
import subprocess
import sys
import time
from pathlib import Path

from firmware_py import can_protocol as cp
from firmware_py.canbus import CanHub, open_bus
from firmware_py.policy import dump_policy
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


def test_60s_episode_cell_policy_reaches_target_b(tmp_path):
    stats = tmp_path / "robot.json"
    with CanHub("hil60") as hub:
        sim = start([BIN / "qnav-sim", "--map", "paper10", "--can", hub.spec, "--lockstep",
                     "--duration", "60", "--start", "0.25,0.25,0", "-q"])
        rob = start([BIN / "qnav-robot", "--can", hub.spec, "--lockstep",
                     "--policy", "policies/paper10_cell.qtab", "--start", "0.25,0.25,0",
                     "--goal-cell", "9,0", "--duration", "59.95", "--stats-json", stats])
        (sim_out, sim_err), (_, rob_err) = finish(sim, rob)
    assert sim.returncode == 0, sim_err
    assert rob.returncode == 0, rob_err
    m = re.search(r"ticks (\d+) \(missed (\d+), stale commands (\d+)", sim_out)
    assert m and m.groups() == ("1200", "0", "0"), sim_out
    s = json.loads(stats.read_text())
    assert s["result"] == "reached"
    assert s["ticks"] == 1200 and s["overruns"] == 0 and s["can_errors"] == 0
    assert [t[2] for t in s["transitions"]] == ["STANDBY", "HOLD", "DRIVING", "GOAL_REACHED", "HOLD"]
    x, y, _ = s["pose_mm"]
    assert abs(x - 4750) < 150 and abs(y - 4750) < 150  # target B's centre (odometry)


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
                     "--start", "0.75,0.75,180", "--goal", "2.25,2.25", "--duration", "29.95"])
        (_, sim_err), (_, rob_err) = finish(sim, rob)
    assert sim.returncode == 0, sim_err
    assert rob.returncode == 0, rob_err
    assert "GOAL_REACHED" in rob_err
    last = (tmp_path / "traj.csv").read_text().strip().splitlines()[-1].split(",")
    x, y = float(last[2]), float(last[3])  # ground truth from the sim
    assert abs(x - 2.25) < 0.2 and abs(y - 2.25) < 0.2


def test_estop_from_another_node_faults_the_robot_process():
    with CanHub("hilestop") as hub:
        sim = start([BIN / "qnav-sim", "--map", "paper10", "--can", hub.spec, "--speed", "4",
                     "--duration", "8", "--start", "0.25,0.25,0", "-q"])  # paced, 4x real time
        rob = start([BIN / "qnav-robot", "--can", hub.spec, "--sim-clock",
                     "--policy", "policies/paper10_cell.qtab", "--start", "0.25,0.25,0",
                     "--goal-cell", "9,0", "--exit-when-done", "--duration", "7.9"])
        bus = open_bus(hub.spec)
        try:
            driving = False
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not driving:  # wait for the robot to drive
                msg = bus.recv(timeout=0.5)
                if msg is not None and cp.frame_name(msg.arbitration_id) == "ControllerHeartbeat":
                    driving = cp.decode(msg)[1]["Ctrl_State"] == 3
            assert driving
            bus.send(cp.encode("EStop", {"EStop_Engage": 1, "EStop_Source": cp.NODE_SIM,
                                         "EStop_Reason": 1}))
            zero_after_fault = None
            while time.monotonic() < deadline and zero_after_fault is None:
                msg = bus.recv(timeout=0.5)
                if msg is not None and cp.frame_name(msg.arbitration_id) == "MotorCommand":
                    sig = cp.decode(msg)[1]
                    if sig["Cmd_LeftSpeed"] == 0 and sig["Cmd_RightSpeed"] == 0:
                        zero_after_fault = True
        finally:
            bus.shutdown()
        (_, sim_err), (_, rob_err) = finish(sim, rob)
    assert zero_after_fault
    assert rob.returncode == 3, rob_err
    assert "FAULT: e-stop engaged" in rob_err
