"""Any-angle shortest paths of the disc robot (ground_station/lab/anyangle.py):
an analytic detour around one obstacle cell, the open room (straight lines),
and the bounds on a real map: straight line <= any-angle <= 8-connected grid path."""

import math

import numpy as np
import pytest

from ground_station.lab.anyangle import anyangle_distances, corner_vertices
from ground_station.maps import GridMap, load_map, octile_distances

R = 150.0


def _pair(cells, a, b):
    idx = {tuple(c): i for i, c in enumerate(cells.tolist())}
    return idx[a], idx[b]


def test_detour_around_one_cell_matches_the_tangent_arc_tangent_path():
    occ = np.zeros((3, 3), dtype=bool)
    occ[1, 1] = True  # 500 mm cells: the obstacle is [500, 1000] x [500, 1000] mm
    gm = GridMap("one", occ)
    # from (250, 750) over the top to (1250, 750): tangent to the 150 mm circle around the corner
    # (500, 1000), the arc to its top, 500 mm straight, and the mirror image
    cs = math.hypot(250, 250)
    tangent = math.sqrt(cs * cs - R * R)
    # the start lies at 225 deg from the corner, the tangent point acos(R / cs) before it,
    # the arc runs from there to the circle's top (90 deg)
    arc = R * (math.radians(225) - math.acos(R / cs) - math.radians(90))
    exact = 2 * (tangent + arc) + 500
    cells, d4 = anyangle_distances(gm, R, arc_vertices=4)
    _, d16 = anyangle_distances(gm, R, arc_vertices=16)
    i, j = _pair(cells, (0, 1), (2, 1))
    # the polygons are circumscribed: never shorter, longer only on the arcs by tan(x)/x
    assert exact - 1e-6 <= d16[i, j] <= d4[i, j]
    assert d4[i, j] - exact <= 2 * arc * (math.tan(math.pi / 16) / (math.pi / 16) - 1) + 1e-6
    assert d16[i, j] - exact < 0.5


def test_open_room_is_straight_lines_and_a_pocket_the_disc_cannot_enter_is_unreachable():
    gm = GridMap("open", np.zeros((4, 5), dtype=bool))
    cells, d = anyangle_distances(gm, R)
    xy = np.stack([(cells[:, 0] + 0.5) * 500, (4 - cells[:, 1] - 0.5) * 500], axis=1)
    assert np.allclose(d, np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)))
    occ = np.zeros((3, 3), dtype=bool)
    occ[0, 1] = occ[1, 0] = True  # cell (0, 0) touches the rest only diagonally: no way for a disc
    cells, d = anyangle_distances(GridMap("pocket", occ), R)
    i, j = _pair(cells, (0, 0), (2, 2))
    assert np.isinf(d[i, j]) and d[j, j] == 0.0


@pytest.mark.parametrize("name", ["paper10", "trap-12x12-s1"])
def test_bounds_on_a_map(name):
    gm = load_map(name)
    cells, d = anyangle_distances(gm, R)
    c = gm.cell_size_m * 1000
    straight = np.hypot(*(cells[:, None] - cells[None]).transpose(2, 0, 1)) * c
    grid = np.stack([octile_distances(gm.occ, int(a), int(b))[cells[:, 1], cells[:, 0]] for a, b in cells]) * c
    ok = np.isfinite(d)
    assert np.array_equal(d, d.T) and np.all(np.diag(d) == 0)
    assert np.all(d[ok] >= straight[ok] - 1e-6)
    assert np.all(d[ok] <= grid[ok] + 1e-6)  # neighbouring centres are always a clear move
    assert np.all(ok == np.isfinite(grid))  # the disc fits through every grid passage here
    assert (d[ok] < grid[ok] - 1.0).mean() > 0.5  # any-angle motion cuts most grid paths


def test_convex_corners_only():
    occ = np.zeros((4, 4), dtype=bool)
    occ[1:3, 1:3] = True  # a 2x2 block: four convex corners, none along its sides
    v = corner_vertices(occ, 500.0, R, 2)
    assert len(v) == 4 * 2
    centre = np.array([1000.0, 1000.0])
    assert np.all(np.linalg.norm(v - centre, axis=1) > math.hypot(500, 500))
