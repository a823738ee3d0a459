"""Q-learning of the recovery decisions (`ground_station.lab.recovery`, issue 47): transitions and
their rewards, the tabular update, the hand-written rules as a table (the baseline) doing what the
rules do, the int8 export, and the failure classification of `qnav bench decisions` (with its
stand-offs and sandwiches)."""

from __future__ import annotations

import numpy as np

from firmware_py.background import Background
from firmware_py.kinds.sector import decide
from firmware_py.kinds.sector.memory import ObstacleMemory
from firmware_py.kinds.sector.recoveries import NO_ROUTE, PlannedTarget
from ground_station.lab.nav.decisions import STANDOFF_PERIODS, Trace, classify, standoff, trace
from ground_station.lab.recovery.config import RecoveryConfig
from ground_station.lab.recovery.qlearn import (
    PERIOD_S,
    int8_table,
    sweep,
    terminal_reward,
    transitions,
    valid_mask,
)
from ground_station.lab.recovery.rule import rule_table
from tests.firmware_py.test_replan import DOOR1, ONE_DOOR, _drive
from tests.support.localplan_rig import CFG

RC = RecoveryConfig()


def test_transitions_cost_the_time_between_decisions_and_end_with_the_outcome():
    ep = {"decisions": [(10, 3, 0), (30, 200, 3)], "periods": 35, "outcome": "no_route", "detour": False}
    (s1, a1, r1, n1), (s2, a2, r2, n2) = transitions(ep, RC)
    assert (s1, a1, n1) == (3, 0, 200) and np.isclose(r1, -RC.cost_per_s * 20 * PERIOD_S)
    assert (s2, a2, n2) == (200, 3, -1) and np.isclose(r2, -RC.cost_per_s * 5 * PERIOD_S + RC.reward_success)
    assert terminal_reward("no_route", True, RC) == RC.reward_wrong_no_route  # a detour existed
    assert terminal_reward("no_route", None, RC) == RC.reward_wrong_no_route  # not blocked: a route exists
    assert terminal_reward("timeout", False, RC) == RC.reward_fail


def test_q_learning_prefers_the_action_whose_episodes_end_well():
    valid = valid_mask()
    q = np.where(valid, 0.0, -1.0)
    s = decide.round_state(0, 1, True, False, True)
    good = [(s, decide.GIVE_WAY, 1.0, -1)] * 5
    bad = [(s, decide.NO_ROUTE, -1.0, -1)] * 5
    for _ in range(20):
        sweep(q, good + bad, 0.1, valid)
    assert q[s].argmax() == decide.GIVE_WAY and q[s, decide.NO_ROUTE] < -0.5
    w = decide.wait_state(0, 0, 0, False)  # bootstraps through the next state's best valid value
    sweep(q, [(w, decide.REPLAN, 0.0, s)] * 50, 0.5, valid)
    assert np.isclose(q[w, decide.REPLAN], q[s].max(), atol=1e-3)


def test_the_rule_table_says_no_route_after_three_still_rounds_as_the_rules_do():
    for decisions in (None, int8_table(rule_table())):
        work = Background(threaded=False)
        pt = PlannedTarget(ONE_DOOR, CFG, work, decisions=decisions)
        rows = _drive(pt, work, ObstacleMemory(CFG), 400, seen=DOOR1)
        assert NO_ROUTE in [r[1] for r in rows] and pt.global_plans == CFG.max_rounds


def test_the_int8_table_keeps_the_greedy_valid_action_and_never_picks_an_invalid_one():
    rng = np.random.default_rng(0)
    q = np.where(valid_mask(), rng.normal(0, 1, (decide.N_STATES, decide.N_ACTIONS)), 5.0)  # invalid large
    t = int8_table(q)
    for s in range(decide.N_STATES):
        valid = decide.VALID[decide.event_of(s)]
        assert t.choose(s) == max(valid, key=lambda a: q[s, a])


def test_a_failure_is_put_down_to_the_decision_that_ended_it():
    tr = Trace(modes=["local"] * 100 + ["wait"] * 500, changes=[(100, "wait", 0, 0, False)])
    assert classify("timeout", tr, 0) == "timeout:waiting"
    tr = Trace(modes=["local"] * 10, changes=[(9, "no route", 1, 9, True)])
    assert classify("no_route", tr, 2) == "declared:cap+gave_way"
    tr = Trace(modes=["local"] * 10, changes=[(9, "no route", 3, 3, False)])
    assert classify("no_route", tr, 0) == "declared:still"


def test_an_episode_that_ends_with_a_mover_at_the_robot_is_a_stand_off():
    near, far = [10.0] * STANDOFF_PERIODS, [500.0] * STANDOFF_PERIODS
    assert standoff([500.0] * 50 + near)
    assert not standoff(far + near[:STANDOFF_PERIODS // 2])  # the last 5 s only
    assert not standoff(near[1:])  # shorter than the window: not judged
    assert standoff(near[:180] + far[:20]) and not standoff(near[:179] + far[:21])  # 90 % of it


def test_the_trace_watches_every_period_of_the_twin_for_the_movers():
    from firmware_py.policy import load_policy
    from ground_station.lab.nav import planned
    from ground_station.lab.nav.controllers import standard_controllers
    from ground_station.lab.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS
    from ground_station.lab.nav.scenario import MoverStyle, episodes
    from ground_station.maps import load_map

    gm = load_map("paper10")
    (ep,) = episodes(gm, 1, 0, 2, 3, movers=MoverStyle(yields=False))
    ctrl = standard_controllers(load_policy("policies/sector.qtab"), ("learnt",))[0]
    seen: list[tuple[float, float, tuple]] = []
    _, _, periods, _, _, _ = planned.rollout(ep, gm, ctrl, BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS,
                                             watch=lambda x, y, m: seen.append((x, y, m.shape)))
    assert len(seen) == periods and all(shape == (3, 6) for _, _, shape in seen)
    assert seen[0][:2] != seen[-1][:2]  # the robot's position as it drives
    (row,) = trace([ep], {gm.name: gm}, ctrl)
    assert row["periods"] == periods and row["standoff"] is False  # reached: no mover stood at it


def _corridor_trace(movers: list[tuple[float, ...]]) -> dict:
    """The learnt stack's trace on a one-cell corridor (row 1, closed at both ends) with the robot in
    its middle driving west and `movers` (not giving way)."""
    from firmware_py.policy import load_policy
    from ground_station.lab.nav.controllers import standard_controllers
    from ground_station.lab.nav.scenario import Episode
    from ground_station.maps import GridMap

    rows = ["@@@@@@@@@@@@", "@..........@", "@@@@@@@@@@@@"]
    gm = GridMap("corridor", np.array([[ch == "@" for ch in r] for r in rows]), cell_size_m=0.5)
    ep = Episode(map=gm.name, start=(3000.0, 750.0, np.pi), goal=(1, 1), goal_mm=(750.0, 750.0),
                 waypoints=[(750.0, 750.0)], movers=movers)
    ctrl = standard_controllers(load_policy("policies/sector.qtab"), ("learnt",))[0]
    (row,) = trace([ep], {gm.name: gm}, ctrl)
    return row


def test_a_robot_pinned_between_two_movers_is_a_sandwich_and_one_mover_a_plain_stand_off():
    # both walk at the robot along the corridor and stand at its body for ever (they do not give way)
    west, east = (1750.0, 750.0, 300.0, 0.0, 150.0, 0.0), (4250.0, 750.0, -300.0, 0.0, 150.0, 0.0)
    both = _corridor_trace([west, east])
    assert not both["success"] and both["standoff"] and both["sandwich"], both
    one = _corridor_trace([west])  # the same stand-off with nothing behind the robot
    assert not one["success"] and one["standoff"] and not one["sandwich"], one


def test_paired_time_counts_who_was_sooner_where_both_succeeded():
    from ground_station.lab.nav.episodes import paired_time

    a = [{"success": True, "time_s": t} for t in (10.0, 20.0, 30.0)] + [{"success": False, "time_s": 5.0}]
    b = [{"success": True, "time_s": t} for t in (12.0, 20.0, 25.0)] + [{"success": True, "time_s": 1.0}]
    got = paired_time(a, b)
    assert got == {"both": 3, "a_faster": 1, "b_faster": 1, "median_diff_s": 0.0, "p_sign": 1.0}


def test_bench_nav_runs_the_learnt_decisions_beside_the_rules_and_exports_the_table(tmp_path):
    import json

    from firmware_py.policy import load_policy
    from ground_station.cli import main
    from ground_station.lab.nav.controllers import standard_controllers, with_recovery_table

    qtab = tmp_path / "rec.qtab"
    qtab.write_bytes(with_recovery_table("policies:sector", int8_table(rule_table())))
    learnt, rules = standard_controllers(load_policy(str(qtab)), ("learnt", "learnt_rules"))
    assert learnt.recovery is not None and rules.recovery is None
    assert decide.META_KEY in learnt.policy("paper10").metadata  # what the robot runs in HIL
    assert decide.META_KEY not in rules.policy("paper10").metadata
    out = tmp_path / "nav.json"
    assert main(["bench", "nav", "--map", "paper10", "--episodes", "2", "--seed", "0", "--policy", str(qtab),
                 "--json", str(out), "--workers", "1"]) == 0
    res = json.loads(out.read_text())
    assert {"learnt", "learnt_rules", "seek_local", "vfh_local"} <= set(res)  # learnt_rules by default
    assert set(res["paired_time_vs_learnt"]["learnt_rules"]) == {"both", "a_faster", "b_faster", "median_diff_s",
                                                                 "p_sign"}


def test_a_no_route_is_traced_with_whether_a_later_waypoint_was_reachable():
    from ground_station.lab.nav.decisions import traced
    from tests.firmware_py.test_replan import ABOVE

    # ONE_DOOR's only door closed (DOOR1): ABOVE, the waypoint, has no route; (4250, 1000) below the wall has
    for later, want in (([ABOVE, (4250, 1000)], True), ([ABOVE, (4250, 2750)], False), ([ABOVE], False),
                        ([(4250, 1000)], False)):  # the waypoint last (the goal) or not an episode's: no later one
        work = Background(threaded=False)
        pt = traced(PlannedTarget(ONE_DOOR, CFG, work))
        pt.later = later
        rows = _drive(pt, work, ObstacleMemory(CFG), 400, seen=DOOR1)
        assert NO_ROUTE in [r[1] for r in rows], later
        assert pt.trace.later_open is want, later
        assert pt.global_plans == CFG.max_rounds  # the trace's own searches leave the robot's recoveries as they were
