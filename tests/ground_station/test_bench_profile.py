"""`qnav bench nav --profile FILE.toml` (issue 44): the bench's twin plays the profile's robot on the same
seeded episodes as the built-in robot's, beside the baselines; a policy the robot would refuse is not
benched on it (one line, exit 2)."""

from __future__ import annotations

import json
from pathlib import Path

from firmware_py.policy import load_policy
from ground_station.cli import main
from ground_station.lab.nav.controllers import kind_controllers
from ground_station.lab.nav.episodes import run_twin, twin_robot
from ground_station.lab.nav.scenario import episodes
from ground_station.maps import load_map

ROOT = Path(__file__).resolve().parents[2]
WIDE = str(ROOT / "firmware_py" / "profiles" / "wide_six.toml")


def _wide_policy(tmp_path, capsys):
    """Train (briefly) and export a sector policy for the wide profile; returns its .qtab path."""
    run = tmp_path / "run"
    assert main(["train", "--recipe", "shipped-sector", "--profile", WIDE, "--steps", "30000", "--out", str(run),
                 "--quiet"]) == 0
    pol = tmp_path / "wide.qtab"
    assert main(["export", str(run), "--out", str(pol), "--no-rollouts"]) == 0
    capsys.readouterr()
    return pol


def test_the_twin_plays_the_profiles_robot_on_the_same_episodes():
    gm = load_map("paper10")
    eps = episodes(gm, 12, 0, 2, 1)
    learnt = kind_controllers(load_policy(str(ROOT / "policies" / "sector.qtab")), ("seek",))[0]
    built_in = run_twin(eps, {gm.name: gm}, learnt)
    assert run_twin(eps, {gm.name: gm}, learnt, twin_robot(None)) == built_in
    wide = run_twin(eps, {gm.name: gm}, learnt, twin_robot(WIDE))
    assert len(wide) == len(built_in) and wide != built_in  # a wider body, a slower turn, other sensors


def test_the_same_episodes_get_waypoints_planned_around_the_wider_body():
    from ground_station.lab.nav.scenario import for_body
    from ground_station.maps.planner import plan_waypoints

    gm = load_map("paper10")
    eps = episodes(gm, 12, 0, 2, 1)
    wide = [for_body(gm, e, 180) for e in eps]
    assert [(e.start, e.goal, e.discs, e.movers) for e in wide] == [(e.start, e.goal, e.discs, e.movers) for e in eps]
    assert [for_body(gm, e, 150).waypoints for e in eps] == [e.waypoints for e in eps]  # the built-in robot's
    differ = [w for w, e in zip(wide, eps, strict=True) if w.waypoints != e.waypoints]
    assert differ and all(w.waypoints == [tuple(map(float, p)) for p in plan_waypoints(
        gm, (int(w.start[0] // 500), 9 - int(w.start[1] // 500)), w.goal, radius_mm=180)] for w in wide)


def test_bench_nav_on_a_profile_reports_the_controllers_and_refuses_a_policy_it_cannot_run(tmp_path, capsys):
    pol = _wide_policy(tmp_path, capsys)
    out = tmp_path / "nav.json"
    assert main(["bench", "nav", "--map", "paper10", "--episodes", "6", "--obstacles", "1", "--movers", "1",
                 "--policy", str(pol), "--profile", WIDE, "--json", str(out), "--png", str(tmp_path / "n.png")]) == 0
    res = json.loads(out.read_text())
    assert res["scenario"]["robot"] == WIDE and res["scenario"]["waypoints_radius_mm"] == 180
    for name in ("learnt", "seek", "vfh", "direct"):
        assert res[name]["episodes"] == 6 and "collision_rate" in res[name] and "success_rate" in res[name]
    capsys.readouterr()
    # the shipped policy was trained for the built-in robot: the wide robot refuses it
    assert main(["bench", "nav", "--map", "paper10", "--episodes", "2", "--profile", WIDE]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"qnav bench: error: policy policies:sector on --profile {WIDE}: policy trained for "
                   f"robot_radius_mm 150 at most, robot profile {WIDE} has 180")
    assert main(["bench", "nav", "--episodes", "2", "--profile", "wobbly"]) == 2
    assert "expected ideal, realistic or a robot profile FILE.toml" in capsys.readouterr().err


def test_bench_hil_on_a_profile_plays_its_robot_beside_the_baselines(tmp_path, capsys):
    """`qnav bench hil --profile FILE.toml`: the lockstep sim and robot play the profile's robot on the
    same seeded episodes, the waypoints keep its body clear, and the baselines run the same episodes."""
    pol = _wide_policy(tmp_path, capsys)
    out = tmp_path / "hil.json"
    assert main(["bench", "hil", "--only", "sector", "--pairs", "2", "--sector-policy", str(pol), "--profile", WIDE,
                 "--profile", "ideal", "--baselines", "seek,vfh", "--max-sim-s", "30", "--json", str(out),
                 "--workers", "1"]) == 0
    res = json.loads(out.read_text())
    assert res["robot"] == WIDE and res["sector"]["episodes"] == 2
    assert [res["baselines"][n]["episodes"] for n in ("seek", "vfh")] == [2, 2]
    # the same episodes as the built-in robot's, planned around the wider body
    from ground_station.lab.bench.hil import sector_episodes
    from ground_station.maps.planner import plan_waypoints

    gm = load_map("paper10")
    for spec, row in zip(sector_episodes(gm, 2, 0), res["sector"]["episodes_detail"], strict=True):
        assert row["start"] == spec["start"] and row["goal"] == spec["goal"]
        assert row["waypoints"] == len(plan_waypoints(gm, tuple(spec["start"]), tuple(spec["goal"]), radius_mm=180))
    for r in (res["sector"], *res["baselines"].values()):
        assert "success" in r and "with_contact" in r
    # the shipped policies were trained for the built-in robot: refused on the wide one, naming both values
    assert main(["bench", "hil", "--only", "cell", "--starts", "1", "--profile", WIDE, "--cell-policy",
                 str(pol)]) == 2
    assert "is a sector policy, expected cell" in capsys.readouterr().err
    assert main(["bench", "hil", "--only", "sector", "--pairs", "1", "--profile", WIDE]) == 2
    assert "robot_radius_mm 150 at most" in capsys.readouterr().err
    assert main(["bench", "hil", "--only", "sector", "--pairs", "1", "--baselines", "learnt"]) == 2


def test_the_lockstep_sim_and_robot_play_the_profile():
    """One bench hil episode on the wide robot is not the built-in robot's (body, wheels, sensors)."""
    from firmware_py.profile import load_profile
    from ground_station.lab.bench.hil import run_episodes, sector_episodes

    gm = load_map("paper10")
    pol = load_policy(str(ROOT / "policies" / "sector.qtab"))
    spec = sector_episodes(gm, 1, 3)
    built_in = run_episodes(gm, pol, "sector", spec, 20.0)[0]
    wide = run_episodes(gm, pol, "sector", spec, 20.0, robot=load_profile(WIDE))[0]
    # measured: built-in 12.95 s over 4 waypoints, wide 15.1 s over 8 (slower turns, denser waypoints)
    assert built_in["result"] == wide["result"] == "reached"
    assert wide["waypoints"] > built_in["waypoints"] and wide["sim_s"] > built_in["sim_s"]
