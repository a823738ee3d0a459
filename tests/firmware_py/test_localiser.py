"""The map in the policy file (firmware_py.mapdata) and the Monte Carlo
localiser's sensor model, against hand-computed cases."""

import math

import pytest

from firmware_py import robot_spec
from firmware_py.control.controller import Controller
from firmware_py.control.localiser import LikelihoodField, Localiser, LocaliserConfig
from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.mapdata import MapDataError, grid_from_metadata, grid_from_rows
from firmware_py.policy import MapGeometry, PolicyError, load_policy
from firmware_py.shipped_policies import shipped_policy
from ground_station.learn.export import policy_bytes, quantise
from tests.support.localiser_ref import log_likelihood, log_p, signed_at

SIGMA, Z_HIT, Z_FLOOR = 50.0, 0.85, 0.15


def value(d_mm: float) -> float:
    """The field's value at distance d (the model's formula, evaluated here by hand)."""
    return math.log(Z_HIT * math.exp(-d_mm * d_mm / (2 * SIGMA * SIGMA)) + Z_FLOOR)


# --- the map in the policy ------------------------------------------------------------

def test_grid_rows_parse_and_render():
    g = grid_from_rows([".@.", "...", "T.W"], 500)
    assert (g.width, g.height, g.cell_mm) == (3, 3, 500)
    assert g.occupied(1, 0) and g.occupied(0, 2) and g.occupied(2, 2) and not g.occupied(1, 1)
    assert g.occupied(-1, 0) and g.occupied(3, 1) and g.occupied(0, 3)  # outside: the outer walls
    assert g.rows() == [".@.", "...", "@.@"]


@pytest.mark.parametrize("rows, why", [
    ([], "non-empty"), ([".@", "."], "row 1 has 1 cells"), ([".x"], "unknown cell 'x'"), ([3], "not a string"),
])
def test_bad_grid_is_one_line_reason(rows, why):
    with pytest.raises(MapDataError, match=why):
        grid_from_rows(rows, 500)


def test_grid_must_match_header_geometry():
    assert grid_from_metadata({}, 500, 3, 3) is None
    with pytest.raises(MapDataError, match="2x1 cells but the header's map geometry is 3x3"):
        grid_from_metadata({"map_grid": [".."]}, 500, 3, 3)


def test_loader_refuses_a_policy_whose_map_does_not_fit_its_header():
    q = quantise(__import__("numpy").zeros((SectorEncoder().n_states, 4)) + 0.5)
    ok = policy_bytes(q, SectorEncoder(), map_geometry=MapGeometry(500, 2, 2), metadata={"map_grid": ["..", ".@"]})
    pol = load_policy(ok)
    assert pol.map_grid is not None and pol.map_grid.occ == bytes([0, 0, 0, 1])
    assert pol.header()["map_grid"] == {"width": 2, "height": 2, "cell_mm": 500, "occupied_cells": 1}
    bad = policy_bytes(q, SectorEncoder(), map_geometry=MapGeometry(500, 3, 2), metadata={"map_grid": ["..", ".@"]})
    with pytest.raises(PolicyError, match="map_grid is 2x2 cells but the header's map geometry is 3x2"):
        load_policy(bad)


def test_shipped_policies_carry_paper10():
    for name in ("sector", "paper10_cell"):
        pol = load_policy(shipped_policy(name))
        assert pol.map_grid is not None
        assert (pol.map_grid.width, pol.map_grid.height, pol.map_grid.cell_mm) == (10, 10, 500)


# --- the likelihood field ---------------------------------------------------------------

@pytest.fixture()
def block():
    """3x3 cells of 500 mm, the centre one occupied: x, y in [500, 1000] mm."""
    return LikelihoodField(grid_from_rows(["...", ".@.", "..."], 500), 25, SIGMA, Z_HIT, Z_FLOOR, 400.0)


def test_distances_by_hand(block):
    assert block.distance_mm(375, 775) == pytest.approx(125.0)  # 125 left of the block, 375 from the west wall
    assert block.distance_mm(1100, 1100) == pytest.approx(math.hypot(100, 100))  # off the block's corner
    assert block.distance_mm(750, 750) == 0.0  # inside the block
    assert block.distance_mm(-10, 750) == 0.0  # inside the outer wall
    assert block.distance_mm(250, 1400) == pytest.approx(100.0)  # 100 below the north wall
    assert block.depth_mm(750, 760) == pytest.approx(240.0)  # inside the block: to its nearest face
    assert block.depth_mm(-10, 750) == pytest.approx(10.0)  # 10 into the outer wall
    assert block.depth_mm(-30, -40) == pytest.approx(50.0)  # off the map's corner


def test_field_values_by_hand(block):
    # raster squares are 25 mm; (387.5, 787.5) is the centre of the square holding (380, 780): 112.5 mm
    assert log_p(block, 380, 780) == pytest.approx(value(112.5), abs=1e-6)
    # on a wall's surface the field's top value, log(z_hit + z_floor) = 0; inside a wall it falls off with
    # the depth as it does with the distance outside (a reading ends on the surface): the square holding
    # (510, 750) is centred 12.5 mm inside the block, (750, 750)'s 237.5 mm; (-10, 750)'s 12.5 mm into the
    # outer wall
    assert log_p(block, 510, 750) == pytest.approx(value(12.5), abs=1e-6)
    assert log_p(block, 750, 750) == pytest.approx(value(237.5), abs=1e-6)
    assert log_p(block, -10, 750) == pytest.approx(value(12.5), abs=1e-6)
    assert value(0.0) == pytest.approx(0.0, abs=1e-6)
    assert signed_at(block, 380, 780) == pytest.approx(112.5) and signed_at(block, 750, 750) == pytest.approx(-237.5)
    # far from everything (capped at 400 mm) and beyond the raster: the outlier floor
    assert log_p(block, -1000, 750) == pytest.approx(math.log(Z_FLOOR))


@pytest.mark.parametrize(("rows", "cell", "res", "max_mm"), [
    (["..@.", "@...", "...@", ".@@."], 500, 25, 400.0),  # reach 1
    ([".@..@", ".....", "@@..."], 250, 24, 400.0),  # reach 2, squares not aligned with the cells
    (["....", "@...", "...."], 300, 40, 400.0),  # squares centred on a free cell's edge with a wall (x = 300)
])
def test_field_squares_equal_the_per_point_distances(rows, cell, res, max_mm):
    """The field is built a map cell at a time (rectangles listed once per cell); each square must hold
    what `distance_mm` / `depth_mm` give for its centre, as a point-by-point build would."""
    f = LikelihoodField(grid_from_rows(rows, cell), res, SIGMA, Z_HIT, Z_FLOOR, max_mm)
    reach = max(1, math.ceil(max_mm / cell))
    assert f.res == res
    walls = 0
    for iy in range(f.ny):
        py = (iy + 0.5) * f.res - f.margin
        for ix in range(f.nx):
            px = (ix + 0.5) * f.res - f.margin
            d = f.distance_mm(px, py, reach)
            inner = d == 0.0
            if inner:
                d = f.depth_mm(px, py, reach)
            d = min(d, max_mm)
            i = iy * f.nx + ix
            walls += inner
            assert f.inside[i] == inner and f.signed[i] == pytest.approx(-d if inner else d, abs=1e-3), (px, py)
            assert f.values[i] == pytest.approx(value(d), abs=1e-6), (px, py)
    assert 0 < walls < f.nx * f.ny


def test_one_reading_by_hand():
    """One 500 mm cell, robot at its centre heading east: only the front
    sensor reads. The cone reports its nearest echo, so the reading's error
    is the signed distance of the ray end nearest to (or deepest into) a
    wall. 100 mm: the centre ray's end point (150 + 100 = 250 mm) is on the
    east wall, in the 25 mm raster square centred 12.5 mm inside it (the side
    rays, +-131 mrad, end 12.5 mm short of it): 12.5 mm off. 50 mm: 50 mm
    short, at (450, 250): its square is centred on (462.5, 262.5), 37.5 mm
    from the east wall, the side rays' 62.5 mm: 37.5 mm off. The best-ray
    model (cone_min=False) takes the wall's square as a hit."""
    cfg = LocaliserConfig(sigma_hit_mm=SIGMA, z_hit=Z_HIT, z_floor=Z_FLOOR, field_res_mm=25, beam_weight=0.6)
    loc = Localiser(grid_from_rows(["."], 500), cfg)
    status = [robot_spec.RANGE_INVALID] * robot_spec.SENSOR_COUNT
    ranges = [0] * robot_spec.SENSOR_COUNT
    status[0] = robot_spec.RANGE_VALID
    ranges[0] = 100
    assert log_likelihood(loc, 250, 250, 0.0, ranges, status) == pytest.approx(0.6 * value(12.5), abs=1e-6)
    ranges[0] = 50
    assert log_likelihood(loc, 250, 250, 0.0, ranges, status) == pytest.approx(0.6 * value(37.5), abs=1e-6)
    ranges[0] = 400  # 300 mm through the wall: the centre ray ends deepest, in the square 312.5 mm inside
    assert log_likelihood(loc, 250, 250, 0.0, ranges, status) == pytest.approx(0.6 * value(312.5), abs=1e-6)
    best = Localiser(grid_from_rows(["."], 500), LocaliserConfig(sigma_hit_mm=SIGMA, z_hit=Z_HIT, z_floor=Z_FLOOR,
                                                                 field_res_mm=25, cone_min=False))
    ranges[0] = 50
    assert log_likelihood(best, 250, 250, 0.0, ranges, status) == pytest.approx(0.6 * value(37.5), abs=1e-6)
    # TOO_FAR and INVALID readings carry no end point
    status[0] = robot_spec.RANGE_TOO_FAR
    assert log_likelihood(loc, 250, 250, 0.0, ranges, status) == 0.0


def test_update_weighs_each_particle_as_the_reference_does():
    """The chunked update (inlined for speed) gives every particle the
    reference model's log weight when there is no motion noise."""
    grid = grid_from_rows(["....", ".@..", "...."], 500)
    cfg = LocaliserConfig(alpha1=0, alpha2=0, alpha3=0, alpha4=0, particles=30, chunk=7, seed=3)
    loc = Localiser(grid, cfg)
    loc.init_pose(1250, 750, 300, std_mm=200, std_mrad=500)
    xs, ys, ths = list(loc.xs), list(loc.ys), list(loc.ths)
    ranges = [300, 250, 180, 900, 2000, 400, 60, 10]
    status = [0, 0, 0, 0, robot_spec.RANGE_TOO_FAR, 0, 0, robot_spec.RANGE_TOO_CLOSE]
    loc.init_global()
    loc._seed, loc._force_update = None, True  # an update on the next tick ...
    loc.xs, loc.ys, loc.ths, loc.global_mode = xs, ys, ths, False  # ... of these particles, tracking
    ticks = 0
    while not loc._finish_due:
        loc.tick((1250, 750, 300), ranges, status)
        ticks += 1
    assert ticks == math.ceil(30 / 7)  # one chunk per tick
    want = [log_likelihood(loc, x, y, t, ranges, status) for x, y, t in zip(xs, ys, ths, strict=True)]
    assert loc.lw == pytest.approx(want, abs=1e-9)
    loc.tick((1250, 750, 300), ranges, status)  # the resample tick
    assert loc.updates == 1 and len(loc.xs) == cfg.particles


def test_believed_pose_follows_odometry_between_updates():
    loc = Localiser(grid_from_rows(["...."], 500))
    loc.init_pose(500, 250, 1571)  # facing north
    loc.tick((500, 250, 1571), [0] * 8, [robot_spec.RANGE_INVALID] * 8)
    loc.tick((500, 280, 1571), [0] * 8, [robot_spec.RANGE_INVALID] * 8)  # 30 mm: below the update distance
    assert loc.pose_mm() == (500, 280, 1571)
    assert loc.goal_vector(500, 1280) == (1000, 0)


# --- the controller --------------------------------------------------------------------

def test_goal_refused_while_not_localised_and_runs_on_odometry_without_a_map():
    pol = load_policy(shipped_policy("sector"))
    ctrl = Controller(policy=pol, start_pose_mm=(1250, 1250, 0))
    assert ctrl.loc is not None and ctrl.loc.localised
    ok, why = ctrl.localise_global(explore=False)
    assert ok, why
    ctrl.armed = True  # the rest of _can_drive is covered by the controller tests
    ok, why = ctrl.go_to(4250, 4250)
    assert not ok and why.startswith("not localised")
    assert not ctrl.status().localised and ctrl.status().localiser == "global"
    off = Controller(policy=pol, localise=False)
    assert off.loc is None and off.nav is off.odom and off.status().localiser == "off"


# --- telemetry and the monitor -----------------------------------------------------------

def test_telemetry_carries_belief_covariance_localised_flag_and_raw_odometry():
    from firmware_py.mavlink.dialect import mavlink2 as m
    from firmware_py.mavlink.params import ParamStore
    from firmware_py.mavlink.telemetry import NodeStats, Telemetry
    from firmware_py.vehicle import VehicleStatus
    from ground_station.monitor.model import VehicleView

    mav = m.MAVLink(None, srcSystem=1, srcComponent=1)
    tel = Telemetry(mav, ParamStore())
    st = VehicleStatus(x_mm=1000, y_mm=2000, odom_x_mm=1300, odom_y_mm=2400, localiser="tracking", localised=True,
                       pose_std_mm=(30, 40), pose_std_mrad=50)
    view = VehicleView(sysid=1)
    out = {}
    for msg_id in (m.MAVLINK_MSG_ID_HEARTBEAT, m.MAVLINK_MSG_ID_LOCAL_POSITION_NED, m.MAVLINK_MSG_ID_ESTIMATOR_STATUS,
                   m.MAVLINK_MSG_ID_LOCAL_POSITION_NED_COV, m.MAVLINK_MSG_ID_ODOMETRY):
        for msg in tel.build(msg_id, 1_000_000, st, NodeStats()):
            msg = mav.parse_char(msg.pack(mav))  # over the wire and back
            out[msg.get_type()] = msg
            view.update(msg, 1.0)
    assert out["ESTIMATOR_STATUS"].flags & m.ESTIMATOR_POS_HORIZ_ABS
    assert out["ESTIMATOR_STATUS"].pos_horiz_accuracy == pytest.approx(0.04)
    cov = out["LOCAL_POSITION_NED_COV"]
    assert (cov.x, cov.y) == pytest.approx((2.0, 1.0)) and cov.covariance[0] == pytest.approx(0.04 ** 2)
    odo = out["ODOMETRY"]
    assert (odo.x, odo.y) == pytest.approx((2.4, 1.3)) and odo.estimator_type == m.MAV_ESTIMATOR_TYPE_NAIVE
    assert view.localised is True and view.localisation_text == "localised=yes std=0.04m odo_err=0.50m"
    lost = VehicleStatus(localiser="global", localised=False, pose_std_mm=(900, 800))
    (msg,) = tel.build(m.MAVLINK_MSG_ID_ESTIMATOR_STATUS, 2_000_000, lost, NodeStats())
    assert not msg.flags & m.ESTIMATOR_POS_HORIZ_ABS and msg.flags & m.ESTIMATOR_CONST_POS_MODE
