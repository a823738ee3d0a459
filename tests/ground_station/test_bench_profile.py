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


def test_the_twin_plays_the_profiles_robot_on_the_same_episodes():
    gm = load_map("paper10")
    eps = episodes(gm, 12, 0, 2, 1)
    learnt = kind_controllers(load_policy(str(ROOT / "policies" / "sector.qtab")), ("seek",))[0]
    built_in = run_twin(eps, {gm.name: gm}, learnt)
    assert run_twin(eps, {gm.name: gm}, learnt, twin_robot(None)) == built_in
    wide = run_twin(eps, {gm.name: gm}, learnt, twin_robot(WIDE))
    assert len(wide) == len(built_in) and wide != built_in  # a wider body, a slower turn, other sensors


def test_bench_nav_on_a_profile_reports_the_controllers_and_refuses_a_policy_it_cannot_run(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", "--recipe", "shipped-sector", "--profile", WIDE, "--steps", "30000", "--out", str(run),
                 "--quiet"]) == 0
    pol = tmp_path / "wide.qtab"
    assert main(["export", str(run), "--out", str(pol), "--no-rollouts"]) == 0
    capsys.readouterr()
    out = tmp_path / "nav.json"
    assert main(["bench", "nav", "--map", "paper10", "--episodes", "6", "--obstacles", "1", "--movers", "1",
                 "--policy", str(pol), "--profile", WIDE, "--json", str(out), "--png", str(tmp_path / "n.png")]) == 0
    res = json.loads(out.read_text())
    assert res["scenario"]["robot"] == WIDE
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
