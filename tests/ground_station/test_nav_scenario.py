"""Navigation scenarios (ground_station/lab/nav/scenario.py, ground_station/nav/obstacles.py) and the twin with
obstacles (ground_station/lab/nav/obstacle_twin.py): seeded and
reproducible, every placed disc meets the documented "detourable"
definition, the twin's movers are the sim's own function, and the twin's
sensing/collision see discs where the pymunk plant does."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from firmware_py import robot_spec
from ground_station.lab.nav import obstacle_twin as tw
from ground_station.lab.nav import scenario as sc
from ground_station.learn.sector.twin import DEFAULT_TW, sense
from ground_station.maps import GridMap, load_map
from ground_station.nav import obstacles as ob
from sim_bridge import obstacles as simobs


@pytest.fixture(scope="module")
def paper10():
    return load_map("paper10")


def test_episodes_are_seeded_and_round_trip_through_json(paper10):
    a = sc.episodes(paper10, 12, 3, 3, 2)
    b = sc.episodes(paper10, 12, 3, 3, 2)
    assert [e.to_json() for e in a] == [e.to_json() for e in b]
    c = sc.episodes(paper10, 12, 4, 3, 2)
    assert [e.to_json() for e in a] != [e.to_json() for e in c]
    back = [sc.Episode.from_json(json.loads(json.dumps(e.to_json()))) for e in a]
    assert [e.to_json() for e in back] == [e.to_json() for e in a]
    assert all(len(e.movers) == 2 and len(e.discs) <= 3 for e in a)
    assert sum(len(e.discs) for e in a) >= 6  # paper10 has room for discs in about half its episodes


def test_every_placed_disc_is_detourable(paper10):
    rooms = load_map("rooms-16x16-s1")
    for gm in (paper10, rooms):
        for e in sc.episodes(gm, 15, 1, 3, 0):
            start = e.start[:2]
            assert ob.detourable(gm, start, e.waypoints, e.discs)
            keep = robot_spec.ROBOT_RADIUS_MM + ob.WAYPOINT_CLEAR_MM
            for x, y, r in e.discs:
                assert ob.DISC_RADIUS_MM[0] <= r <= ob.DISC_RADIUS_MM[1]
                for px, py in [start, *e.waypoints]:
                    assert math.hypot(px - x, py - y) >= r + keep - 1e-6


def test_a_disc_in_a_one_cell_corridor_is_not_detourable():
    occ = np.ones((3, 8), dtype=bool)
    occ[1, :] = False  # one corridor, 500 mm wide
    gm = GridMap(name="corridor", occ=occ)
    start, wps = (250.0, 750.0), [(1250.0, 750.0), (2250.0, 750.0), (3750.0, 750.0)]
    assert ob.detourable(gm, start, wps, [])
    assert not ob.detourable(gm, start, wps, [(3000.0, 750.0, 120.0)])  # blocks the corridor
    occ2 = np.ones((5, 8), dtype=bool)
    occ2[1:4, :] = False  # three cells wide: room to pass
    gm2 = GridMap(name="hall", occ=occ2)
    mid = 1250.0
    assert ob.detourable(gm2, (250.0, mid), [(1250.0, mid), (2250.0, mid), (3750.0, mid)],
                         [(3000.0, mid, 120.0)])
    assert not ob.detourable(gm2, (250.0, mid), [(1250.0, mid), (2250.0, mid), (3750.0, mid)],
                             [(2250.0, mid + 100.0, 120.0)])  # sits on a waypoint


def test_twin_movers_are_the_sim_function(paper10):
    occ = np.ascontiguousarray(paper10.occ, dtype=np.uint8)
    rng = np.random.default_rng(0)
    discs = np.array([[1250.0, 3750.0, 150.0]])
    for trial in range(20):
        movers = np.array([[x, y, vx, vy, 150.0] for x, y, vx, vy in
                           zip(rng.uniform(300, 4700, 3), rng.uniform(300, 4700, 3),
                               rng.uniform(-600, 600, 3), rng.uniform(-600, 600, 3), strict=True)])
        a, b = movers.copy(), movers.copy()
        for _ in range(50):
            simobs.step_movers(a, occ, 500.0, discs, 2500.0, 2500.0, 150.0, 0.05)
            tw.step_movers(b, occ, 500.0, discs, 2500.0, 2500.0, 150.0, 0.05)
        np.testing.assert_array_equal(a, b, err_msg=f"trial {trial}")


def test_movers_bounce_and_never_walk_into_the_robot():
    occ = np.zeros((4, 4), dtype=np.uint8)
    movers = np.array([[1000.0, 1000.0, 600.0, 0.0, 150.0]])
    rx, ry = 1500.0, 1000.0
    flips = 0
    for _ in range(200):
        vx = movers[0, 2]
        simobs.step_movers(movers, occ, 500.0, np.zeros((0, 3)), rx, ry, 150.0, 0.05)
        flips += movers[0, 2] != vx
        d = math.hypot(movers[0, 0] - rx, movers[0, 1] - ry)
        assert d >= 300.0 + simobs.YIELD_MARGIN_MM - 1e-9
        assert 150.0 <= movers[0, 0] <= 2000.0 - 150.0
    assert flips >= 4  # bounced between the west wall and the robot, again and again


def test_a_mover_the_robot_came_up_to_steps_away_instead_of_freezing():
    """A yielding mover inside the robot's yield margin (the robot drove up to it) walks away: it froze
    before (every step, away too, ended inside the margin and was refused), and in a maze corridor a
    robot waiting for it said "no route" where a route exists (issue 47); the twin's copy agrees."""
    occ = np.zeros((4, 4), dtype=np.uint8)
    movers = np.array([[1170.0, 1000.0, 400.0, 0.0, 150.0]])  # 330 mm from the robot: inside 300 + 60
    twin = movers.copy()
    rx, ry = 1500.0, 1000.0
    for _ in range(10):
        d0 = math.hypot(movers[0, 0] - rx, movers[0, 1] - ry)
        simobs.step_movers(movers, occ, 500.0, np.zeros((0, 3)), rx, ry, 150.0, 0.05)
        tw.step_movers(twin, occ, 500.0, np.zeros((0, 3)), rx, ry, 150.0, 0.05)
        assert math.hypot(movers[0, 0] - rx, movers[0, 1] - ry) >= d0  # never nearer
    np.testing.assert_array_equal(movers, twin)
    assert movers[0, 0] < 1170.0 - 100.0  # it stepped back, out of the margin


def test_a_mover_that_does_not_yield_walks_its_line_and_stops_only_at_contact():
    """`yields` = 0 (qnav bench nav --no-yield): it keeps walking at the robot, stands while it would
    overlap it, and walks on once the robot is out of its way; the twin's compiled copy agrees."""
    occ = np.zeros((4, 8), dtype=np.uint8)
    movers = np.array([[500.0, 1000.0, 600.0, 0.0, 150.0, 0.0]])
    twin = movers.copy()
    rx, ry = 1500.0, 1000.0
    for _ in range(40):
        simobs.step_movers(movers, occ, 500.0, np.zeros((0, 3)), rx, ry, 150.0, 0.05)
        tw.step_movers(twin, occ, 500.0, np.zeros((0, 3)), rx, ry, 150.0, 0.05)
        assert math.hypot(movers[0, 0] - rx, movers[0, 1] - ry) >= 300.0 - 1e-9  # never overlapping
    np.testing.assert_array_equal(movers, twin)
    assert movers[0, 2] == 600.0 and abs(movers[0, 0] - (rx - 300.0)) <= 30.0  # pressed against it, not bounced
    for _ in range(10):  # the robot moves away: it walks on along its line
        simobs.step_movers(movers, occ, 500.0, np.zeros((0, 3)), rx, 3000.0, 150.0, 0.05)
    assert movers[0, 0] > rx - 300.0 + 100.0


def test_scenario_movers_carry_their_style_and_old_five_value_movers_yield(paper10):
    style = sc.MoverStyle(speed=(800.0, 1000.0), yields=False)
    ep = sc.episodes(paper10, 3, 1, 0, 3, movers=style)[0]
    for _x, _y, vx, vy, _r, yields in ep.movers:
        assert 800.0 - 0.1 <= math.hypot(vx, vy) <= 1000.0 + 0.1 and yields == 0.0
    assert sc.Episode.from_json(json.loads(json.dumps(ep.to_json()))) == ep
    assert simobs.mover_array([(1.0, 2.0, 3.0, 4.0, 5.0)]).tolist() == [[1.0, 2.0, 3.0, 4.0, 5.0, 1.0]]


def test_twin_sees_and_hits_a_disc_like_the_pymunk_plant():
    from sim_bridge.plant import Plant, SimConfig
    from sim_bridge.sensors import RangeParams
    from sim_bridge.world import Pose

    occ = np.zeros((8, 8), dtype=bool)
    disc = (2600.0, 2000.0, 150.0)
    plant = Plant(occ, SimConfig(seed=0, ranges=RangeParams(noise_std_mm=0.0)), Pose(2.0, 2.0, 0.0))
    plant.obstacles = simobs.ObstacleLayer(plant.world, [disc], [])
    sim_front = plant.ranges.true_ranges_mm()[0]
    o = np.zeros((8, 8), dtype=np.uint8)
    ranges = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
    status = np.zeros_like(ranges)
    which = np.ones(robot_spec.SENSOR_COUNT, dtype=np.bool_)
    tw.sense_obs(o, 8, 8, 500.0, 2000.0, 2000.0, 0.0, which, ranges, status,
                 np.array([disc]), np.zeros((0, 5)), DEFAULT_TW)
    assert sim_front is not None and abs(ranges[0] - sim_front) <= 2.0  # 600 - 150 - 150 = 300 mm
    assert abs(ranges[0] - 300) <= 3
    bare = np.zeros_like(ranges)
    sense(o, 8, 8, 500.0, 2000.0, 2000.0, 0.0, which, bare, np.zeros_like(status), DEFAULT_TW)
    assert bare[0] > ranges[0]  # the grid alone does not see it
    x, y = 2000.0, 2000.0
    hit = False
    for _ in range(40):
        x, y, _th, _d, hit = tw.move_obs(o, 8, 8, 500.0, x, y, 0.0, 0, np.array([disc]), np.zeros((0, 5)), DEFAULT_TW)
        if hit:
            break
    assert hit and x == pytest.approx(2600.0 - 300.0, abs=25.0)


def test_episode_arrays_pack_waypoints_and_remaining_lengths(paper10):
    eps = sc.episodes(paper10, 5, 0, 2, 1)
    a = sc.episode_arrays(eps, {"paper10": paper10})
    for i, e in enumerate(eps):
        n = len(e.waypoints)
        assert a["nwp"][i] == n and a["nd"][i] == len(e.discs) and a["nm"][i] == len(e.movers)
        np.testing.assert_allclose(a["wp"][i, :n], e.waypoints)
        path = sum(math.dist(p, q) for p, q in zip(e.waypoints[:-1], e.waypoints[1:], strict=True))
        assert a["rem"][i, 0] == pytest.approx(path)
        assert a["rem"][i, n - 1] == 0.0


def test_twin_rollouts_depend_only_on_their_episodes(paper10):
    from firmware_py.policy import load_policy
    from ground_station.lab.nav.controllers import standard_controllers
    from ground_station.lab.nav.episodes import run_twin

    pol = load_policy(str(robot_spec_policy()))
    learnt = standard_controllers(pol, ("learnt",))[0]
    eps = sc.episodes(paper10, 10, 2, 3, 2)
    whole = run_twin(eps, {"paper10": paper10}, learnt)
    halves = run_twin(eps[:5], {"paper10": paper10}, learnt) + run_twin(eps[5:], {"paper10": paper10}, learnt)
    assert whole == halves


def robot_spec_policy():
    from firmware_py.shipped_policies import shipped_policy

    return shipped_policy("sector")

