"""The `odrive` drive backend against the sim's two emulated ODrive axes (sim_bridge/odrive_axes.py,
written from ODrive's CANSimple protocol, not from the robot's backend): lockstep in one process on
python-can's virtual bus, and across processes (qnav-sim and qnav-robot, each with --profile) on a
python-can-remote hub."""

from __future__ import annotations

import math
import random
import signal
import subprocess
import sys
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
from sim_bridge.odrive_axes import CLOSED_LOOP, IDLE

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
ODRIVE = ROOT / "firmware_py" / "profiles" / "odrive.toml"


@pytest.fixture(scope="module")
def odrive_profile():
    return load_profile(ODRIVE)


def test_the_robot_reaches_goals_through_two_odrive_axes(odrive_profile):
    gm, pol = paper10(), cell_policy()
    for seed in range(3):
        start, goal = far_trip(gm, pol, random.Random(seed))
        ep = run_episode(gm.occ, pol, start, [goal], robot=odrive_profile, max_sim_s=90, seed=seed)
        assert ep.result == "reached" and ep.contacts == 0, (seed, ep.result, ep.transitions[-3:])


def _rig(profile, seed=1):
    gm, pol = paper10(), cell_policy()
    start, goal = far_trip(gm, pol, random.Random(seed))
    return LockstepRig(gm.occ, pol, start, [goal], robot=profile, seed=seed)


def test_arming_sets_velocity_control_and_closed_loop_and_every_tick_feeds_the_axes(odrive_profile):
    with _rig(odrive_profile) as rig:
        rig.run_until(3_000_000)
        assert rig.ctrl.state == CtrlState.DRIVING
        for axis in rig.plant.odrive.axes:
            assert axis.state == CLOSED_LOOP and axis.control_mode == 2 and axis.input_mode == 1
            assert axis.commands[0x0D] >= 55  # Set_Input_Vel on every tick of the 3 s but the first
        # the right axis turns the other way for the robot to drive straight (right_sign = -1)
        left, right = (a.input_vel for a in rig.plant.odrive.axes)
        assert rig.plant.motors.target[0] > 0 or rig.plant.motors.target[1] > 0
        assert left * right <= 0 or abs(left) < 1e-6 or abs(right) < 1e-6


@pytest.mark.parametrize("what, words", [("error:0x40", "left axis 0 (ODrive node 0): axis error 0x40 (MOTOR_FAILED)"),
                                         ("silent", "left axis 0 (ODrive node 0): no ")])
def test_an_axis_error_or_a_silent_axis_mid_drive_is_a_fault_naming_the_axis_and_the_wheels_stop(
        odrive_profile, what, words):
    with _rig(odrive_profile) as rig:
        rig.run_until(2_000_000)
        assert rig.ctrl.state == CtrlState.DRIVING
        t_fault = rig.plant.time_us + 10_000
        rig.plant.odrive.faults = [(t_fault, what, "left")]
        rig.run_until(t_fault + 1_000_000)
        tr = rig.first_transition_to(CtrlState.FAULT)
        assert tr is not None and words in tr.cause, list(rig.ctrl.transitions)[-3:]
        timeout_us = rig.ctrl.cfg.sensor_timeout_ms * 1000
        # an error arrives with the next heartbeat (every 100 ms); silence once the timeout has passed
        assert tr.t_us - t_fault <= (150_000 if what.startswith("error") else timeout_us + 250_000)
        right = rig.plant.odrive.axes[1]
        assert right.state == IDLE and right.input_vel == 0.0  # zero velocity, then IDLE
        assert rig.plant.motors.target == [0.0, 0.0]


def test_odrive_across_processes_on_the_hub(tmp_path):
    from ground_station.canhub import CanHub

    with CanHub("odrive") as hub:
        common = ["--can", hub.spec, "--lockstep", "--profile", ODRIVE]
        sim = subprocess.Popen([BIN / "qnav-sim", "--map", "paper10", "--duration", "40", "-q",
                                "--start", "0.25,0.25,90", "--trajectory", tmp_path / "traj.csv", *common],
                               stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        rob = subprocess.Popen([BIN / "qnav-robot", "--policy", "policies:paper10_cell", "--start", "0.25,0.25,90",
                                "--goal-cell", "2,2", "--exit-when-done", "--mavlink", "none", "--localiser", "off",
                                "--stats-json", tmp_path / "stats.json", *common],
                               stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            _, rob_err = rob.communicate(timeout=120)
        finally:
            sim.send_signal(signal.SIGINT)  # the sim writes its trajectory and exits 130
            sim.communicate(timeout=30)
            for p in (sim, rob):
                if p.poll() is None:
                    p.kill()
                    p.wait()
    assert rob.returncode == 0, rob_err[-2000:]
    import json

    stats = json.loads((tmp_path / "stats.json").read_text())
    assert stats["result"] == "reached" and stats["drive_backend"] == "odrive" and stats["drive_bad_frames"] == 0
    last = (tmp_path / "traj.csv").read_text().strip().splitlines()[-1].split(",")
    assert abs(float(last[2]) - 1.25) < 0.25 and abs(float(last[3]) - 3.75) < 0.25  # cell (2, 2) of 10 rows


@pytest.mark.wallclock  # the robot on the wall clock: at load 11 the script's heartbeat came 285 ms late (FAULT)
def test_a_script_playing_two_odrives_from_the_protocol_alone_is_driven_to_a_goal(tmp_path):
    """tools/odrive_pair.py plays two ODrive axes from ODrive's CANSimple documentation (it imports
    neither the robot's backend nor the sim) in an empty field, wall clock, on a hub."""
    import json

    from ground_station.canhub import CanHub

    assert "firmware_py.drives" not in (ROOT / "tools" / "odrive_pair.py").read_text()
    with CanHub("odpair") as hub:
        pair = subprocess.Popen([sys.executable, ROOT / "tools" / "odrive_pair.py", "--can", hub.spec,
                                 "--start", "0.25,0.25,0", "--duration", "60", "--json", tmp_path / "end.json"],
                                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            rob = subprocess.run([BIN / "qnav-robot", "--can", hub.spec, "--profile", ODRIVE, "--policy",
                                  "policies:sector", "--start", "0.25,0.25,0", "--goal", "2.25,0.25", "--localiser",
                                  "off", "--mavlink", "none", "--exit-when-done", "--duration", "40"],
                                 capture_output=True, text=True, timeout=90)
        finally:
            pair.send_signal(signal.SIGINT)
            pair.communicate(timeout=30)
    assert rob.returncode == 0 and "GOAL_REACHED" in rob.stderr, rob.stderr[-2000:]
    end = json.loads((tmp_path / "end.json").read_text())
    x, y, _ = end["pose"]
    assert math.hypot(x - 2.25, y - 0.25) < 0.2  # the script's own kinematics put the robot at the goal
    for axis in end["axes"].values():
        assert axis["received"]["Set_Controller_Mode"] >= 1 and axis["received"]["Set_Input_Vel"] > 20
        assert axis["state"] == 1 and axis["error"] == 0  # IDLE again after the goal
