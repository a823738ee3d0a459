"""Localisation in lockstep HIL at the realistic plant profile (one encoder
3 % long, 10 % slip, 10 mm range noise, 2 % dropout): the robot reaches its
goals on the localiser's pose while dead reckoning drifts, seeded."""

import math

import pytest

from firmware_py import robot_spec
from firmware_py.policy import load_policy
from firmware_py.shipped_policies import shipped_policy
from ground_station.bench.hil import random_pairs, run_cell_set, run_global_set, run_sector_set
from ground_station.rigs.lockstep import cell_policy, paper10, run_episode
from sim_bridge.profiles import PROFILES, profile

REALISTIC = PROFILES["realistic"]


def test_realistic_profile_is_what_the_docs_say():
    assert REALISTIC.encoder_scale == (1.03, 1.0) and REALISTIC.slip_std == 0.10
    assert REALISTIC.range_noise_mm == 10.0 and REALISTIC.range_dropout == 0.02
    with pytest.raises(ValueError, match="unknown plant profile 'nope'; known: ideal, realistic"):
        profile("nope")


def test_cell_policy_reaches_on_the_localiser_where_odometry_drifts():
    gm = paper10()
    pol = cell_policy()
    goal = robot_spec.cell_center_mm(*pol.goals[0], gm.height, pol.cell_mm)  # target A (2, 2)
    start = (4.75, 0.25, math.pi)  # cell (9, 9): across the map from A
    ep = run_episode(gm.occ, pol, start, [goal], max_sim_s=60, seed=0, profile=REALISTIC)
    assert ep.success, ep.result
    assert ep.belief_error_mm <= 120 and ep.belief_error_max_mm <= 200
    assert ep.odom_error_mm > 3 * ep.belief_error_mm  # the drift the localiser removed
    cpu = sorted(ep.step_cpu_us)
    assert cpu and len(cpu) == ep.ticks  # one Controller.step per tick, each timed


def test_bench_sets_at_the_realistic_profile_report_belief_and_truth():
    gm = paper10()
    rows = run_sector_set(gm, load_policy(shipped_policy("sector")), 2, 7, 60.0, profile=REALISTIC)
    rows += run_cell_set(gm, cell_policy(), 1, 7, 60.0, profile=REALISTIC)
    assert len(rows) == 6
    for r in rows:
        assert r["success"], r
        assert r["belief_error_mm"] <= 120
        assert r["step_cpu_p99_us"] > 0


def test_global_localisation_episode_runs_and_reports():
    """The global set's bookkeeping on one episode (convergence itself is a
    benchmark figure, not asserted here)."""
    gm = paper10()
    rows = run_global_set(gm, load_policy(shipped_policy("sector")), 1, 0, limit_s=2.0, profile=REALISTIC)
    (r,) = rows
    assert r["armed"] is True and r["global"] is True
    assert r["start"] == list(random_pairs(gm.occ, 1, 0)[0][0])
    assert r["localised_after_s"] is None or r["localised_after_s"] <= 2.0


def test_tight_goal_tolerance_ends_close_to_the_goal_in_truth():
    """With the localiser the robot's belief is good enough for a 40 mm goal
    tolerance (GOAL_TOL_MM): the true end error stays within the acceptance's
    120 mm bound at the realistic profile."""
    from firmware_py.vehicle import VehicleConfig

    gm = paper10()
    pol = cell_policy()
    goal = robot_spec.cell_center_mm(*pol.goals[3], gm.height, pol.cell_mm)  # target D (9, 7)
    ep = run_episode(gm.occ, pol, (0.25, 4.75, 0.0), [goal], max_sim_s=60, seed=1, profile=REALISTIC,
                     vehicle=VehicleConfig(goal_tolerance_mm=40))
    assert ep.success, ep.result
    assert ep.final_error_mm <= 120
