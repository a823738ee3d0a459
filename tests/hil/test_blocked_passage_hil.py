"""A door closed by something the map does not show, in lockstep HIL (pymunk plant, the robot's own
controller and sector policy on its own map, `qnav bench nav`'s episode code): with another door the
robot re-plans over the whole map and gets there through it; with none it says "no route" (STATUSTEXT,
mission ended in HOLD) without touching anything (`firmware_py.kinds.sector.recoveries.PlannedTarget`'s recoveries)."""

from __future__ import annotations

import math

import pytest

from firmware_py import robot_spec
from firmware_py.policy import load_policy
from firmware_py.shipped_policies import resolve_policy_spec
from ground_station.lab.nav.controllers import standard_controllers
from ground_station.lab.nav.episodes import run_hil
from ground_station.lab.nav.scenario import WAYPOINT_CLEAR_MM, make_episode
from ground_station.maps import load_map

# 10 x 7 cells of 500 mm; a wall along row 3 with a door at col 2 and (TWO_DOORS) one at col 8
ROWS = {"two_doors": ["." * 10] * 3 + ["@@.@@@@@.@"] + ["." * 10] * 3,
        "one_door": ["." * 10] * 3 + ["@@.@@@@@@@"] + ["." * 10] * 3}
DOOR_DISC = (1250.0, 1750.0, 200.0)  # fills door 1 but for 50 mm each side: the robot (300 mm) cannot pass


def _episode(tmp_path, name: str):
    path = tmp_path / f"{name}.map"
    path.write_text("type octile\nheight 7\nwidth 10\nmap\n" + "\n".join(ROWS[name]) + "\n")
    gm = load_map(str(path))
    ep = make_episode(gm, (2, 5), (2, 1), math.pi / 2, seed=3)  # below door 1 facing it, goal above
    ep.map = str(path)
    ep.discs = [DOOR_DISC]
    ep.waypoints = [ep.goal_mm]  # in sight of the start (the station's plan puts one in the door)
    keep = robot_spec.ROBOT_RADIUS_MM + WAYPOINT_CLEAR_MM + DOOR_DISC[2]
    assert all(math.hypot(x - DOOR_DISC[0], y - DOOR_DISC[1]) >= keep for x, y in [ep.start[:2], *ep.waypoints])
    return ep, {ep.map: gm}


@pytest.fixture(scope="module")
def learnt():
    return standard_controllers(load_policy(str(resolve_policy_spec("policies:sector"))), ("learnt",))[0]


def test_a_closed_door_is_gone_round_through_the_other(tmp_path, learnt):
    ep, maps = _episode(tmp_path, "two_doors")
    [row] = run_hil([ep], maps, learnt, max_sim_s=90.0)
    assert row["outcome"] == "success", row
    assert row["contacts"] == 0
    assert row["path_ratio"] > 2.5  # 2 m straight through door 1; round through door 2 it is ~8 m


def test_no_door_left_is_reported_as_no_route_without_a_contact(tmp_path, learnt):
    ep, maps = _episode(tmp_path, "one_door")
    [row] = run_hil([ep], maps, learnt, max_sim_s=60.0)
    assert row["outcome"] == "no_route", row
    assert row["result"].startswith("stopped: no route to (1250,2750)")
    assert row["contacts"] == 0 and row["time_s"] < 30.0
