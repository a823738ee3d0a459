"""`qnav bench controller`'s step-compute section (issue 29): the code runs both
policies on the lockstep rig and pools per-tick step CPU; figures are the
benchmark's to report, never a test's to judge."""

from __future__ import annotations

from firmware_py.policy import load_policy
from firmware_py.shipped_policies import resolve_policy_spec
from ground_station.lab.bench.controller import PlannerOff, _pcts, step_compute
from ground_station.lab.nav.controllers import standard_controllers


def test_step_compute_runs_the_cell_and_the_sector_policy_with_obstacles():
    r = step_compute(str(resolve_policy_spec("policies:sector")), 1, 3, 2)
    assert r["nav"]["ticks"] > 100
    assert r["nav"]["obstacles"] == 3 and r["nav"]["movers"] == 2 and len(r["nav"]["outcomes"]) == 1
    # the baselines take trips until they have as many ticks as the sector side (at most 10 for 1 episode)
    assert r["cell"]["trips"] >= 1 and (r["cell"]["ticks"] >= r["nav"]["ticks"] or r["cell"]["trips"] == 10)
    off = r["nav_planner_off"]
    assert len(off["outcomes"]) >= 1 and (off["ticks"] >= r["nav"]["ticks"] or len(off["outcomes"]) == 10)
    for side in ("cell", "nav", "nav_planner_off"):
        assert 0 < r[side]["p50_us"] <= r[side]["p99_us"] <= r[side]["max_us"]
    assert r["nav_over_cell_p99"] == r["nav"]["p99_us"] / r["cell"]["p99_us"]
    assert r["planner_on_over_off_p99"] == r["nav"]["p99_us"] / r["nav_planner_off"]["p99_us"]
    assert r["nav"]["background_runs"] > 0  # the planner did search (between ticks)


def test_the_planner_off_baseline_keeps_the_map_and_drops_the_planner():
    learnt = standard_controllers(load_policy(str(resolve_policy_spec("policies:sector"))), ("learnt",))[0]
    on, off = learnt.policy("paper10"), PlannerOff(learnt).policy("paper10")
    assert on.kind_config is not None and off.kind_config is None
    assert off.map_grid is not None and off.map_grid == on.map_grid  # the localiser still runs
    assert off.table == on.table


def test_percentiles_of_a_known_list():
    assert _pcts(list(range(1, 101))) == {"p50_us": 51, "p99_us": 100, "max_us": 100, "ticks": 100}
    assert _pcts([])["ticks"] == 0
