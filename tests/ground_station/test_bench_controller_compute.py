"""`qnav bench controller`'s step-compute section (issue 29): the code runs both
policies on the lockstep rig and pools per-tick step CPU; figures are the
benchmark's to report, never a test's to judge."""

from __future__ import annotations

from firmware_py.shipped_policies import resolve_policy_spec
from ground_station.bench.controller import _pcts, step_compute


def test_step_compute_runs_the_cell_and_the_sector_policy_with_obstacles():
    r = step_compute(str(resolve_policy_spec("policies:sector")), 1, 3, 2)
    assert r["cell"]["ticks"] > 100 and r["nav"]["ticks"] > 100
    assert r["nav"]["obstacles"] == 3 and r["nav"]["movers"] == 2 and len(r["nav"]["outcomes"]) == 1
    for side in ("cell", "nav"):
        assert 0 < r[side]["p50_us"] <= r[side]["p99_us"] <= r[side]["max_us"]
    assert r["nav_over_cell_p99"] == r["nav"]["p99_us"] / r["cell"]["p99_us"]


def test_percentiles_of_a_known_list():
    assert _pcts(list(range(1, 101))) == {"p50_us": 51, "p99_us": 100, "max_us": 100, "ticks": 100}
    assert _pcts([])["ticks"] == 0
