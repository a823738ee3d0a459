"""Global localisation in HIL: seeded unknown starts on paper10 in the
lockstep rig (pymunk plant) at the realistic plant profile."""

import pytest


def test_global_localisation_converges_in_hil_at_the_realistic_profile():
    """Three seeded unknown starts on paper10 in the lockstep rig (the
    realistic plant profile): each localises within 10 s sim time, within
    150 mm of the true pose, without wall contact."""
    pytest.importorskip("pymunk")
    from firmware_py.policy import load_policy
    from firmware_py.shipped_policies import shipped_policy
    from ground_station.lab.bench.hil import run_global_set
    from ground_station.maps import load_map
    from sim_bridge.profiles import profile

    rows = run_global_set(load_map("paper10"), load_policy(shipped_policy("sector")), 3, seed=0,
                          limit_s=10.0, profile=profile("realistic"))
    assert [r["success"] for r in rows] == [True] * 3, rows
