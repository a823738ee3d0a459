"""Localisation in lockstep HIL at the realistic plant profile (one encoder
3 % long, 10 % slip, 10 mm range noise, 2 % dropout): the robot reaches its
goals on the localiser's pose while dead reckoning drifts, seeded."""

import math
from pathlib import Path

import pytest

from firmware_py import robot_spec
from firmware_py.policy import load_policy
from firmware_py.shipped_policies import shipped_policy
from ground_station.lab.bench.hil import (
    cell_episodes,
    random_pairs,
    run_batch,
    run_global_set,
    sector_episodes,
)
from ground_station.lab.rigs.lockstep import CELL_POLICY, cell_policy, paper10, run_episode
from sim_bridge.profiles import PROFILES, profile

REALISTIC = PROFILES["realistic"]
ROOT = Path(__file__).resolve().parents[2]


def test_realistic_profile_is_what_the_docs_say():
    """docs/can-protocol.md's table of the profiles' values agrees with sim_bridge/profiles.PROFILES."""
    text = (ROOT / "docs" / "can-protocol.md").read_text()
    rows = {cells[1]: cells[3:5] for cells in (ln.split("|") for ln in text.splitlines())
            if len(cells) == 6 and cells[1].strip().startswith("`--")}

    def documented(option: str, column: int) -> list[float]:
        (cells,) = [v for k, v in rows.items() if option in k]
        return [float(x) for x in cells[column].split(",")]

    for column, name in enumerate(("ideal", "realistic")):
        prof = PROFILES[name]
        assert documented("--enc-scale-left", column) == list(prof.encoder_scale)
        assert documented("--slip", column) == [prof.slip_std]
        assert documented("--noise-mm", column) == [prof.range_noise_mm]
        assert documented("--dropout", column) == [prof.range_dropout]
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
    """Through run_batch, the job `qnav bench hil` farms out to its engine."""
    gm = paper10()
    job = {"map": "paper10", "guidance": "path", "max_sim_s": 60.0, "profile": "realistic",
           "goal_tolerance_mm": None, "localise": True, "png_dir": None}
    rows = run_batch({**job, "kind": "sector", "policy": str(shipped_policy("sector")),
                      "episodes": sector_episodes(gm, 2, 7)})
    rows += run_batch({**job, "kind": "cell", "policy": str(CELL_POLICY),
                       "episodes": cell_episodes(gm, cell_policy(), 1, 7)})
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
