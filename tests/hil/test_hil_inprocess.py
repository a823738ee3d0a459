"""HIL in one process: pymunk plant + RobotNode/Controller threads on a real
python-can virtual bus, lockstep handshake as specified."""

import math
from array import array

import numpy as np
import pytest

from firmware_py import can_protocol as cp
from firmware_py import robot_spec
from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.policy import MapGeometry, dump_policy, load_policy
from firmware_py.shipped_policies import shipped_policy
from ground_station.lab.rigs.lockstep import cut_sensors_after, run_episode
from ground_station.maps import load_map
from tests.support.controller_rig import sector_seek_policy

PAPER10 = load_map("paper10")
H = PAPER10.height


def centre_m(col, row):
    x, y = robot_spec.cell_center_mm(col, row, H)
    return x / 1000, y / 1000


def forward_only_policy():
    enc = SectorEncoder()
    vals = array("b", [100, 0, 0, 0] * enc.n_states)
    return load_policy(dump_policy(enc, vals, "int8", 0.01, policy_id=7, map_geometry=MapGeometry(500, 10, 10)))


@pytest.mark.parametrize("target", ["A", "D"])
def test_cell_policy_reaches_paper10_target_without_contact(target):
    pol = load_policy(shipped_policy("paper10_cell"))
    goal = robot_spec.cell_center_mm(*PAPER10.targets[target], H, pol.cell_mm)
    ep = run_episode(PAPER10.occ, pol, (*centre_m(0, 9), 0.5), [goal], max_sim_s=90)
    assert ep.result == "reached", ep.transitions
    assert ep.contacts == 0
    assert ep.final_error_mm <= robot_spec.GOAL_TOLERANCE_MM + 50  # ground truth, not odometry
    # lockstep: one command per tick, each carrying its tick's counter
    assert [c[3] for c in ep.commands] == list(range(len(ep.commands)))


def test_sector_decisions_drive_the_plant_to_a_goal():
    # hand-made seek policy in an open 8x8 arena: exercises encoder -> table -> wheel speeds
    # (the trained sector policy on paper10 runs in `qnav bench hil` and the cross-process test)
    arena = np.zeros((8, 8), dtype=bool)
    goal = robot_spec.cell_center_mm(6, 2, 8)
    start = robot_spec.cell_center_mm(1, 6, 8)
    ep = run_episode(arena, sector_seek_policy(), (start[0] / 1000, start[1] / 1000, -math.pi / 2),
                     [goal], max_sim_s=60)
    assert ep.result == "reached", ep.transitions
    assert ep.contacts == 0
    assert ep.final_error_mm <= robot_spec.GOAL_TOLERANCE_MM + 50
    speeds = {(c[1], c[2]) for c in ep.commands}
    assert (400, 400) in speeds and speeds <= set(robot_spec.ACTION_WHEEL_SPEEDS_MM_S) | {(0, 0)}


def test_sensor_cut_zeroes_commands_within_one_period_after_timeout():
    pol = load_policy(shipped_policy("paper10_cell"))
    goal = robot_spec.cell_center_mm(*PAPER10.targets["B"], H, pol.cell_mm)
    cut_us = 2_000_000
    ep = run_episode(PAPER10.occ, pol, (*centre_m(0, 9), 0.0), [goal], max_sim_s=6,
                     frames_hook=cut_sensors_after(cut_us))
    assert ep.result.startswith("FAULT: sensor data stale"), ep.result
    last_fresh = cut_us - robot_spec.CONTROL_PERIOD_US
    timeout_us = 250_000
    before = [c for c in ep.commands if c[0] < cut_us]
    assert any(c[1] or c[2] for c in before)  # it was driving
    first_zero_after = min(c[0] for c in ep.commands
                           if c[0] > last_fresh + timeout_us and c[1] == 0 and c[2] == 0)
    assert first_zero_after <= last_fresh + timeout_us + robot_spec.CONTROL_PERIOD_US
    assert all(c[1] == 0 and c[2] == 0 for c in ep.commands if c[0] >= first_zero_after)
    fault = [t for t in ep.transitions if t[2] == "FAULT"]
    assert fault and fault[0][0] == first_zero_after


def test_bumper_stops_the_robot():
    from firmware_py.vehicle import VehicleConfig

    goal = robot_spec.cell_center_mm(9, 9, H)
    # facing the west outer wall, 100 mm away, with a policy that only drives forward: the collision
    # monitor stops it short of the wall ...
    start = (*centre_m(0, 9), math.pi)
    ep = run_episode(PAPER10.occ, forward_only_policy(), start, [goal], max_sim_s=5, stop_when_done=False)
    assert ep.contacts == 0 and ep.result != "stopped: bumper pressed"
    assert all(c[1] == 0 and c[2] == 0 for c in ep.commands[-20:])  # held, not driving on
    # ... and with the monitor off (CM_STOP_MM = CM_SLOW_MM = 0) the bumper does it
    off = VehicleConfig(collision_stop_mm=0, collision_slow_mm=0)
    ep = run_episode(PAPER10.occ, forward_only_policy(), start, [goal], max_sim_s=5, stop_when_done=False,
                     vehicle=off)
    assert ep.contacts >= 1
    hold = [t for t in ep.transitions if t[3] == "bumper pressed"]
    assert hold and hold[0][1:3] == ("DRIVING", "HOLD")
    t_hold = hold[0][0]
    assert all(c[1] == 0 and c[2] == 0 for c in ep.commands if c[0] >= t_hold)
    assert ep.result == "stopped: bumper pressed"


def test_estop_frame_stops_and_latches():
    pol = load_policy(shipped_policy("paper10_cell"))
    goal = robot_spec.cell_center_mm(*PAPER10.targets["B"], H, pol.cell_mm)
    sent = []

    def inject(rig):
        if rig.time_us == 1_000_000 and not sent:
            msg = cp.encode("EStop", {"EStop_Engage": 1, "EStop_Source": cp.NODE_SIM, "EStop_Reason": 4})
            rig.send(msg)
            rig.plant.handle(msg)  # the motor driver on the same bus latches too
            sent.append(rig.time_us)
        if rig.time_us == 2_000_000:  # released: the controller stays latched
            msg = cp.encode("EStop", {"EStop_Engage": 0, "EStop_Source": cp.NODE_SIM, "EStop_Reason": 4})
            rig.send(msg)
            rig.plant.handle(msg)

    ep = run_episode(PAPER10.occ, pol, (*centre_m(0, 9), 0.0), [goal], max_sim_s=4,
                     before_tick=inject, stop_when_done=False)
    fault = [t for t in ep.transitions if t[2] == "FAULT"]
    assert fault and fault[0][3] == "e-stop engaged" and fault[0][0] == 1_000_000
    assert all(c[1] == 0 and c[2] == 0 for c in ep.commands if c[0] >= 1_000_000)
    assert ep.transitions[-1][2] == "FAULT"  # still latched after the release
