"""The `dronecan` backends against the sim's DroneCAN ESC and rangefinder nodes (sim_bridge/
dronecan_boards.py: nodes of the DroneCAN project's own library): lockstep in one process on
python-can's virtual bus, and across processes on a python-can-remote hub, where the library's own
node monitor sees the robot as a node with its name."""

from __future__ import annotations

import dataclasses
import json
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from firmware_py.profile import load_profile
from firmware_py.vehicle import CtrlState
from ground_station.lab.rigs.lockstep import (
    LockstepRig,
    cell_policy,
    far_trip,
    paper10,
    run_episode,
)

dronecan = pytest.importorskip("dronecan", reason="the dronecan extra (pip install 'qnav[dronecan]')")

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
DRONECAN = ROOT / "firmware_py" / "profiles" / "dronecan.toml"


def _variant(drive: str, sensors: str, command: str = "rpm"):
    p = load_profile(DRONECAN)
    return dataclasses.replace(p, drive=dataclasses.replace(p.drive, backend=drive, command=command),
                               sensors=dataclasses.replace(p.sensors, backend=sensors))


@pytest.mark.parametrize("drive, sensors, command", [("dronecan", "dronecan", "rpm"), ("dronecan", "dronecan", "raw"),
                                                     ("qnav", "dronecan", "rpm"), ("odrive", "dronecan", "rpm"),
                                                     ("dronecan", "qnav", "rpm")])
def test_the_robot_reaches_goals_through_each_combination_of_backends(drive, sensors, command):
    prof = _variant(drive, sensors, command)
    gm, pol = paper10(), cell_policy()
    for seed in (1,):  # one far trip each: the backends' frames every tick, there and back in the plant
        start, goal = far_trip(gm, pol, random.Random(seed))
        ep = run_episode(gm.occ, pol, start, [goal], robot=prof, max_sim_s=90, seed=seed)
        assert ep.result == "reached" and ep.contacts == 0, (seed, ep.result, ep.transitions[-3:])


def _rig(seed=1):
    gm, pol = paper10(), cell_policy()
    start, goal = far_trip(gm, pol, random.Random(seed))
    return LockstepRig(gm.occ, pol, start, [goal], robot=load_profile(DRONECAN), seed=seed)


@pytest.mark.parametrize("what, words", [("error:1", "left ESC 0, DroneCAN node 10: health ERROR"),
                                         ("silent", "left ESC 0, DroneCAN node 10: esc.Status none for")])
def test_an_esc_reporting_an_error_or_falling_silent_is_a_fault_naming_it_and_the_wheels_stop(what, words):
    with _rig() as rig:
        rig.run_until(2_000_000)
        assert rig.ctrl.state == CtrlState.DRIVING
        t_fault = rig.plant.time_us + 10_000
        rig.plant.dronecan.faults = [(t_fault, what, "left")]
        rig.run_until(t_fault + 2_500_000)  # NodeStatus (health) comes at 1 Hz of the library's clock
        tr = rig.first_transition_to(CtrlState.FAULT)
        assert tr is not None and words in tr.cause, list(rig.ctrl.transitions)[-3:]
        assert rig.plant.motors.target == [0.0, 0.0]  # zero commanded, then the ESCs' timeout


def test_range_measurements_fill_the_sectors_by_sensor_id_and_reading_type():
    """A sector's reading comes from the Measurement with its sensor_id; TOO_FAR reads as the maximum."""
    gm, pol = paper10(), cell_policy()
    start, _goal = far_trip(gm, pol, random.Random(1))
    with LockstepRig(gm.occ, pol, start, [], robot=load_profile(DRONECAN)) as rig:  # no goal: standing still
        rig.run_until(500_000)
        inp = rig.node.inputs.snapshot()
        truth = rig.plant.ranges.read()  # the plant's readings at this pose (10 mm noise per sample)
        assert [s for s in inp.range_status] == [s for _, s in truth]
        assert all(abs(a - b) <= 60 for a, (b, _) in zip(inp.ranges_mm, truth, strict=True))
        assert len(set(inp.ranges_mm)) > 3  # eight sectors, not one reading copied


def test_dronecan_across_processes_and_the_librarys_node_monitor_sees_the_robot(tmp_path):
    from dronecan.app.node_monitor import NodeMonitor

    from firmware_py.canbus import open_bus
    from ground_station.canhub import CanHub
    from tests.support.dronecan_bus import PythonCanBusDriver

    with CanHub("dronecan") as hub:
        common = ["--can", hub.spec, "--lockstep", "--profile", DRONECAN]
        sim = subprocess.Popen([BIN / "qnav-sim", "--map", "paper10", "--duration", "60", "-q", "--start",
                                "0.25,0.25,90", "--max-speed", "4", *common],
                               stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        rob = subprocess.Popen([BIN / "qnav-robot", "--policy", "policies:paper10_cell", "--start", "0.25,0.25,90",
                                "--goal-cell", "2,2", "--exit-when-done", "--mavlink", "none", "--localiser", "off",
                                "--stats-json", tmp_path / "stats.json", *common],
                               stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        node = dronecan.node.Node(PythonCanBusDriver(open_bus(hub.spec)), node_id=42)
        monitor = NodeMonitor(node)
        try:
            seen = None
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and rob.poll() is None:
                node.spin(0.1)
                entry = monitor.get(100) if monitor.exists(100) else None
                if entry is not None and entry.info is not None:
                    seen = entry
                    break
            _, rob_err = rob.communicate(timeout=120)
        finally:
            node.close()
            sim.send_signal(signal.SIGINT)
            sim.communicate(timeout=30)
            for p in (sim, rob):
                if p.poll() is None:
                    p.kill()
                    p.wait()
    assert seen is not None, "the node monitor never got the robot's GetNodeInfo"
    assert seen.info.name.decode() == "org.qnav.robot" and seen.status.health == 0
    assert rob.returncode == 0, rob_err[-2000:]
    stats = json.loads((tmp_path / "stats.json").read_text())
    assert stats["result"] == "reached" and stats["drive_backend"] == "dronecan" and stats["can_errors"] == 0
    assert stats["dronecan_node_info_answers"] >= 1 and stats["dronecan_bad_transfers"] == 0
