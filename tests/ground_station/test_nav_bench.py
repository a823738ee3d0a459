"""The controllers of `qnav bench nav` (ground_station/lab/nav/controllers.py),
the bench's contract (table + JSON keys + PNG), the HIL episode loop on the
lockstep rig with obstacles."""

from __future__ import annotations

import json

import numpy as np
import pytest

from firmware_py import robot_spec
from firmware_py.kinds.base import best_action
from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.policy import load_policy
from firmware_py.shipped_policies import shipped_policy
from ground_station.lab.nav import controllers as nc
from ground_station.lab.nav.episodes import run_hil, run_twin, summarise
from ground_station.lab.nav.scenario import episodes
from ground_station.learn.sector.evaluate import seek_table
from ground_station.maps import load_map
from tests.support.cli import run_qnav

ENC = SectorEncoder(15, (0, 1, 7), (100, 400))


def _state(enc: SectorEncoder, bearing_mrad: int, front: int, left: int, right: int) -> int:
    ranges = [2000] * robot_spec.SENSOR_COUNT
    ranges[0], ranges[1], ranges[7] = front, left, right
    return enc.encode(bearing_mrad, ranges, [robot_spec.RANGE_VALID] * robot_spec.SENSOR_COUNT)


def test_vfh_table_steers_to_the_free_valley_nearest_the_target():
    q = nc.vfh_table(ENC)
    act = lambda *a: int(np.argmax(q[_state(ENC, *a)]))  # noqa: E731
    assert act(0, 1500, 1500, 1500) == nc.FORWARD  # target ahead, free
    assert act(0, 50, 1500, 300) == nc.LEFT  # blocked ahead: the wider side
    assert act(0, 50, 300, 1500) == nc.RIGHT
    assert act(2500, 1500, 1500, 1500) == nc.LEFT  # target far left: turn to it
    assert act(-2500, 1500, 1500, 1500) == nc.RIGHT
    assert act(800, 1500, 50, 1500) == nc.FORWARD  # target left, left blocked, ahead free: the valley ahead
    assert act(800, 1500, 1500, 1500) == nc.LEFT  # target left, left free: toward it
    assert not q[:, nc.REVERSE].any()
    with pytest.raises(ValueError, match="front range sensor"):
        nc.vfh_table(SectorEncoder(15, (1, 7), (100, 400)))


def test_standard_controllers_share_the_policy_encoder_and_export_as_qtab():
    pol = load_policy(str(shipped_policy("sector")))
    ctrls = nc.standard_controllers(pol)
    assert [c.name for c in ctrls] == ["learnt", "seek", "vfh", "direct"]
    assert [c.guidance for c in ctrls] == ["path", "path", "path", "direct"]
    np.testing.assert_array_equal(ctrls[1].q, seek_table(pol.encoder))
    for c in ctrls:
        exported = c.policy("paper10")
        assert exported.encoder == pol.encoder
        for s in range(0, pol.n_states, 7):  # the robot's greedy choice is the table's
            assert best_action(exported.row(s)) == int(np.argmax(c.q[s]))
    learnt = ctrls[0]
    assert all(best_action(pol.row(s)) == int(np.argmax(learnt.q[s])) for s in range(pol.n_states))


def test_hil_episodes_with_obstacles_on_the_lockstep_rig():
    gm = load_map("paper10")
    eps = episodes(gm, 2, 5, 3, 2)
    pol = load_policy(str(shipped_policy("sector")))
    learnt = nc.standard_controllers(pol, ("learnt",))[0]
    rows = run_hil(eps, {"paper10": gm}, learnt)
    assert len(rows) == 2
    for r in rows:
        assert r["outcome"] in ("success", "collision", "timeout", "stopped")
        assert r["success"] == (r["result"] == "reached" and r["contacts"] == 0)
        assert r["time_s"] > 0 and r["movers"] == 2
    s = summarise(rows + run_twin(eps, {"paper10": gm}, learnt))
    assert s["episodes"] == 4 and 0.0 <= s["success_rate"] <= 1.0


def test_hil_counts_a_drive_into_a_disc_as_a_collision():
    """An episode with a disc right on the first leg and the seek table, which
    ignores ranges: the bumper must register it (with the robot's collision monitor off; on, it
    stops short of the disc and the episode is no collision)."""
    from firmware_py.vehicle import VehicleConfig
    from ground_station.lab.nav.scenario import Episode

    gm = load_map("paper10")
    # row 0 (north corridor) is free end to end: start (0,0) -> goal (3,0), a disc at (1.0 m, 4.75 m)
    ep = Episode(map="paper10", start=(250.0, 4750.0, 0.0), goal=(3, 0), goal_mm=(1750.0, 4750.0),
                 waypoints=[(1750.0, 4750.0)], discs=[(1000.0, 4750.0, 150.0)], movers=[])
    pol = load_policy(str(shipped_policy("sector")))
    seek = nc.standard_controllers(pol, ("seek",))[0]
    hil = run_hil([ep], {"paper10": gm}, seek, vehicle=VehicleConfig(collision_stop_mm=0, collision_slow_mm=0))[0]
    twin = run_twin([ep], {"paper10": gm}, seek)[0]
    assert hil["collision"] and not hil["success"] and hil["contacts"] >= 1
    guarded = run_hil([ep], {"paper10": gm}, seek, max_sim_s=15.0)[0]
    assert not guarded["collision"] and guarded["contacts"] == 0
    assert twin["outcome"] == "collision"


def _qnav(*argv: str) -> tuple[int, str]:
    code, out, err = run_qnav(*argv)
    return code, out + err


def test_bench_nav_contract_table_json_png(tmp_path):
    js = tmp_path / "nav.json"
    code, out = _qnav("bench", "nav", "--map", "paper10", "--map", "rooms-16x16-s1", "--episodes", "12",
                      "--obstacles", "2", "--movers", "1", "--controllers", "learnt,seek,vfh,direct", "--json", str(js))
    assert code == 0, out
    assert "twin learnt" in out and "twin vfh" in out and "paper10 seek" in out
    d = json.loads(js.read_text())
    assert d["scenario"]["maps"] == ["paper10", "rooms-16x16-s1"]
    assert d["scenario"]["obstacles"] == 2 and d["scenario"]["movers"] == 1
    for c in ("learnt", "seek", "vfh", "direct"):
        for key in ("success_rate", "collision_rate", "path_ratio_mean", "episodes"):
            assert key in d[c]
        assert d[c]["episodes"] == 24
        assert d["per_map"]["paper10"][c]["episodes"] == 12
    png = js.with_suffix(".png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bench_nav_hil_part_and_bad_input(tmp_path):
    js = tmp_path / "nav.json"
    code, out = _qnav("bench", "nav", "--map", "paper10", "--episodes", "3", "--hil", "--hil-episodes", "2",
                      "--controllers", "learnt", "--json", str(js))
    assert code == 0, out
    d = json.loads(js.read_text())
    assert d["hil"]["learnt"]["episodes"] == 2 and d["hil"]["twin_same_episodes"]["learnt"]["episodes"] == 2
    assert "hil learnt" in out
    code, out = _qnav("bench", "nav", "--controllers", "learnt,dwa")
    assert code == 2 and "dwa" in out and len(out.strip().splitlines()) == 1
    code, out = _qnav("bench", "nav", "--map", "no-such-map")
    assert code == 2 and "no-such-map" in out
    code, out = _qnav("bench", "nav", "--policy", "policies:paper10_cell", "--episodes", "2")
    assert code == 2 and "sector policy" in out


def test_intervals_and_the_paired_test_are_the_textbook_ones():
    """The 95 % Wilson interval and the exact McNemar test bench nav prints beside every rate."""
    from ground_station.lab.nav.episodes import mcnemar_exact, wilson95

    assert wilson95(957, 1000) == [0.9426, 0.9679]  # the headline learnt rate: [0.943, 0.968]
    assert wilson95(0, 20) == [0.0, 0.1611] and wilson95(20, 20) == [0.8389, 1.0]  # sound at the ends
    ok, ko = {"success": True}, {"success": False}
    paired = mcnemar_exact([ok] * 45 + [ko] * 11 + [ok] * 4, [ko] * 45 + [ok] * 11 + [ok] * 4)
    assert paired["a_only"] == 45 and paired["b_only"] == 11
    assert abs(paired["p_exact"] - 5.378e-6) < 0.001e-6  # issue 32's 45 vs 11 episodes: p = 5e-6
    assert mcnemar_exact([ok, ko], [ok, ko])["p_exact"] == 1.0  # no discordant pair: no evidence


def test_bench_nav_runs_the_sector_memory_policy_in_hil_beside_its_hand_written_rule(tmp_path):
    js = tmp_path / "smem.json"
    code, out = _qnav("bench", "nav", "--policy", "policies:sector_memory", "--map", "rooms-16x16-s1",
                      "--episodes", "1", "--hil", "--hil-episodes", "1", "--obstacles", "0", "--movers", "0",
                      "--json", str(js))
    assert code == 0, out
    d = json.loads(js.read_text())
    for c in ("learnt", "rule"):  # the shipped table and the same mode rules with hand-written moves
        assert d["hil"][c]["episodes"] == 1 and d["hil"]["per_map"]["rooms-16x16-s1"][c]["episodes"] == 1
        assert c not in d  # no twin figure: its trainer's twin is a grid world
    assert "learnt_only" in d["hil"]["paired_vs_learnt"]["rule"]
    assert "runs in HIL only" in out
    code, out = _qnav("bench", "nav", "--policy", "policies:sector_memory", "--episodes", "1")
    assert code == 2 and "--hil" in out and len(out.strip().splitlines()) == 1
    code, out = _qnav("bench", "nav", "--policy", "policies:sector_memory", "--controllers", "seek", "--hil")
    assert code == 2 and "learnt, rule" in out


def test_the_twin_applies_the_robots_collision_monitor_stop_zone():
    """`planned.monitor_stops` is the robot's collision monitor on the twin's action: a forward step
    toward a reading inside the stop zone is stopped, a turn in place never, a clear front never;
    a remembered point between the cones counts as on the robot (Controller._outputs)."""
    from firmware_py.control.collision import MapCorners
    from firmware_py.kinds.sector.config import LocalPlannerConfig
    from firmware_py.kinds.sector.guard import FORWARD, TURN_LEFT
    from firmware_py.kinds.sector.memory import ObstacleMemory
    from firmware_py.vehicle import VehicleConfig
    from ground_station.lab.nav.planned import grid_of, monitor_stops

    n = robot_spec.SENSOR_COUNT
    gm = load_map("paper10")
    corners = MapCorners(grid_of(gm))
    x, y = 2750, 2750  # a free cell's centre, facing east (0 mrad)
    stop = VehicleConfig().collision_stop_mm
    far = ([2000] * n, [robot_spec.RANGE_TOO_FAR] * n)
    near = ([stop // 2] + [2000] * (n - 1), [robot_spec.RANGE_VALID] + [robot_spec.RANGE_TOO_FAR] * (n - 1))
    memory = ObstacleMemory(LocalPlannerConfig())
    assert not monitor_stops(FORWARD, x, y, 0, *far, memory, corners)
    assert monitor_stops(FORWARD, x, y, 0, *near, memory, corners)
    assert not monitor_stops(TURN_LEFT, x, y, 0, *near, memory, corners)
    memory.points[(0, 0)] = (x + robot_spec.ROBOT_RADIUS_MM + stop // 2, y + 60, 0)  # ahead, no sensor on it
    assert monitor_stops(FORWARD, x, y, 0, *far, memory, corners)


def test_the_twins_monitor_shortcut_answers_as_the_robots_monitor():
    """`monitor_stops` skips `collision.limit` for a straight step when nothing lies within
    stop_mm + radius of the centre: over random readings, remembered points and poses on paper10
    its answer equals the monitor's own (limit(...) == "stop")."""
    import random

    from firmware_py.control import collision
    from firmware_py.control.collision import mapped_readings
    from firmware_py.kinds.sector.config import LocalPlannerConfig
    from firmware_py.kinds.sector.memory import ObstacleMemory
    from firmware_py.vehicle import VehicleConfig
    from ground_station.lab.nav.planned import grid_of, monitor_stops

    rng = random.Random(7)
    n = robot_spec.SENSOR_COUNT
    corners = collision.MapCorners(grid_of(load_map("paper10")))
    cfg = VehicleConfig()
    stops = 0
    for _ in range(3000):
        x, y, th = rng.randint(200, 4800), rng.randint(200, 4800), rng.randint(-3141, 3141)
        status = [rng.choice((robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_FAR, robot_spec.RANGE_TOO_CLOSE))
                  for _ in range(n)]
        ranges = [rng.randint(20, 400) for _ in range(n)]
        memory = ObstacleMemory(LocalPlannerConfig())
        for k in range(rng.randint(0, 4)):
            memory.points[(k, 0)] = (x + rng.randint(-400, 400), y + rng.randint(-400, 400), 0)
        for action, (left, right) in enumerate(robot_spec.ACTION_WHEEL_SPEEDS_MM_S):
            seen = [(px, py) for px, py, _ in memory.points.values()]
            seen += corners.near(x, y, cfg.collision_slow_mm + 2 * robot_spec.ROBOT_RADIUS_MM)
            near = collision.robot_frame(seen, (x, y, th)) if seen else []
            mapped = mapped_readings(corners.grid, (x, y, th), ranges, status)  # as the controller's
            want = collision.limit(left, right, ranges, status, cfg.collision_stop_mm, cfg.collision_slow_mm,
                                   cfg.collision_slow_pct, near, mapped)[2] == "stop"
            assert monitor_stops(action, x, y, th, ranges, status, memory, corners) == want
            stops += want
    assert stops > 100  # the draw does reach the stop zone
