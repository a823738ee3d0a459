"""A body touching the robot's flank in the blind gap between two sensor cones (a non-yielding
mover that walked up to the robot and stands): by the twin's own ray model the sensors read it only
along the nearer cone's edge, some 10-40 mm off, never as touching. The collision monitor still holds
a step that would rub into it (a reading under CONTACT_MM counts the rim across the gaps beside its
cone), while a wall alongside at a corridor's usual distance holds nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_py import robot_spec
from firmware_py.control.collision import (
    CONTACT_MM,
    FAR_MM,
    MapCorners,
    limit,
    mapped_readings,
    robot_frame,
    travel_gap_mm,
)
from firmware_py.mapdata import grid_from_rows
from ground_station.lab.nav.obstacle_twin import sense_obs
from ground_station.learn.sector.twin import DEFAULT_TW

R = robot_spec.ROBOT_RADIUS_MM
N = robot_spec.SENSOR_COUNT
CELL = 500.0


def _sense(bodies: list[tuple[float, float, float]], occ: np.ndarray | None = None,
           at: tuple[float, float] = (5000.0, 5000.0)) -> tuple[list[int], list[int]]:
    """The eight readings of a robot at `at` facing east (+x) with discs (x, y, r) about it."""
    grid = np.zeros((20, 20), dtype=np.uint8) if occ is None else occ
    ranges, status = np.zeros(N, dtype=np.int64), np.zeros(N, dtype=np.int64)
    discs = np.array(bodies, dtype=np.float64).reshape(-1, 3)
    sense_obs(grid, grid.shape[0], grid.shape[1], CELL, at[0], at[1], 0.0, np.ones(N, dtype=np.bool_),
              ranges, status, discs, np.zeros((0, 6)), DEFAULT_TW)
    return ranges.tolist(), status.tolist()


def _touching(contact_deg: float, radius: float, gap_mm: float = 1.0) -> tuple[float, float, float]:
    a, d = math.radians(contact_deg), R + radius + gap_mm
    return 5000.0 + d * math.cos(a), 5000.0 + d * math.sin(a), radius


@pytest.mark.parametrize("radius", [100.0, 150.0, 260.0])
@pytest.mark.parametrize("contact_deg", [15.0, 22.5, 30.0, 60.0, 67.5, 75.0, 80.0])
@pytest.mark.parametrize("side", [1, -1])
def test_a_body_touching_the_rim_in_a_blind_gap_holds_the_step_that_rubs_into_it(radius, contact_deg, side):
    ahead = _sense([_touching(side * contact_deg, radius)])
    assert travel_gap_mm(*ahead, reverse=False) == 0  # ahead of the axle: a step ahead rubs into it
    behind = _sense([_touching(side * (180.0 - contact_deg), radius)])
    assert travel_gap_mm(*behind, reverse=True) == 0  # behind it: a step back does
    if contact_deg <= 30.0 or contact_deg == 67.5:
        # seen by the front cones only, or mid-gap by the two cones either side of it (the side and
        # a diagonal): the gap it is in is known, and moving away from it stays free
        assert travel_gap_mm(*ahead, reverse=True) == FAR_MM
        assert travel_gap_mm(*behind, reverse=False) == FAR_MM


@pytest.mark.parametrize("radius", [100.0, 150.0])
def test_a_mover_at_the_flank_is_read_tens_of_millimetres_off(radius):
    """The case the monitor used to miss: in the middle of the gap the body is read as a valid
    20-40 mm by both cones, whose reading points lie beside the swept corridor; below 20 mm the
    reading was taken as 20 (now 0). A step ahead then rubbed into it: all 14 collisions of the
    no-yield bench (seed 0) before."""
    ranges, status = _sense([_touching(-67.5, radius)])
    for i in (6, 7):  # the -90 and -45 degree sensors, either side of the gap
        assert status[i] == robot_spec.RANGE_VALID and robot_spec.RANGE_MIN_MM <= ranges[i] < CONTACT_MM


def test_a_wall_alongside_at_a_corridors_distance_holds_nothing():
    occ = np.zeros((20, 20), dtype=np.uint8)
    occ[9, :] = 1  # a wall along x, its south face at y = 10 * CELL... (row 9 spans y 5000..5500)
    for side_gap in (CONTACT_MM + 10, 100.0):
        ranges, status = _sense([], occ, at=(5000.0, 5000.0 - R - side_gap))
        assert travel_gap_mm(ranges, status, reverse=False) == FAR_MM
        assert travel_gap_mm(ranges, status, reverse=True) == FAR_MM


def test_a_reading_the_robot_map_explains_fills_no_gap():
    """A block of the robot's map 38 mm off the left flank (its corner just behind the axle, its
    face alongside ahead: paper10, where the robot stood at the corner for good): the monitor has the
    map's corners as points, and a step ahead along the face is free once the caller says which
    readings the map explains. The same reading from a mover (not on the map) holds the step."""
    rows = ["." * 20] * 20
    rows[9] = "." * 10 + "@" + "." * 9  # the block x 5000..5500, y 5000..5500 (row 0 north)
    grid = grid_from_rows(rows, int(CELL))
    occ = np.array([[c == "@" for c in row] for row in rows], dtype=np.uint8)
    at = (5010.0, 5000.0 - R - 38.0)
    ranges, status = _sense([], occ, at=at)
    assert status[2] == robot_spec.RANGE_VALID and ranges[2] < CONTACT_MM  # the left sensor
    pose = (int(at[0]), int(at[1]), 0)
    mapped = mapped_readings(grid, pose, ranges, status)
    assert mapped[2]
    corners = robot_frame(MapCorners(grid).near(pose[0], pose[1], 1000), pose)
    assert limit(400, 400, ranges, status, 50, 200, 50, corners, mapped)[2] == ""
    assert limit(400, 400, ranges, status, 50, 200, 50, corners)[2] == "stop"  # not known to be the map's
