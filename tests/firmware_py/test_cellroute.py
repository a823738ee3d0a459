"""The sector-memory kind's route on the robot's map (firmware_py.kinds.sector_memory.cellroute): the distance field,
the straight sub-goal, the field built off the tick, and the Bug steering on sub-goals (and back
on the goal when one cannot be reached)."""

from __future__ import annotations

from firmware_py import robot_spec
from firmware_py.background import Background
from firmware_py.kinds.base import DriveTick
from firmware_py.kinds.sector_memory import SUBGOAL_SLACK_MOVES, SectorMemoryDriver
from firmware_py.kinds.sector_memory.cellroute import (
    UNREACHABLE,
    CellRoute,
    distance_field,
    straight_subgoal,
)
from firmware_py.mapdata import OccupancyGrid
from firmware_py.policy import load_policy, on_robot_map
from firmware_py.shipped_policies import shipped_policy
from tests.support.background import pending

C = 500
# row 0 is north; a wall down column 3 from row 1: from (2, 4) to (4, 4) the way is round its top
ROWS = [".....",
        "...#.",
        "...#.",
        "...#.",
        "...#."]
GRID = OccupancyGrid(C, 5, 5, bytes(1 if ch == "#" else 0 for row in ROWS for ch in row))
N = robot_spec.SENSOR_COUNT


def test_distance_field_counts_moves_round_the_wall():
    f = distance_field(GRID, (4, 4))
    assert f[4 * 5 + 4] == 0 and f[0 * 5 + 4] == 4 and f[0 * 5 + 3] == 5
    assert f[4 * 5 + 2] == 10  # up column 2, across the top, down column 4
    assert f[1 * 5 + 3] == UNREACHABLE  # a wall cell
    assert set(distance_field(GRID, (3, 2))) == {UNREACHABLE}  # a goal in a wall reaches nothing


def test_straight_subgoal_is_the_end_of_the_straight_run_down_the_field():
    f = distance_field(GRID, (4, 4))
    assert straight_subgoal(f, 5, 5, (2, 4)) == (2, 0)  # north to the top row, where the route turns
    assert straight_subgoal(f, 5, 5, (2, 0)) == (4, 0)
    assert straight_subgoal(f, 5, 5, (4, 0)) == (4, 4)
    assert straight_subgoal(f, 5, 5, (4, 4)) == (4, 4)  # at the goal
    assert straight_subgoal(f, 5, 5, (3, 2)) is None  # a wall cell: off the field
    open_grid = OccupancyGrid(C, 3, 3, bytes(9))
    g = distance_field(open_grid, (2, 0))
    # from (0, 2) east and north are both two moves down: the way the robot faces wins the tie
    assert straight_subgoal(g, 3, 3, (0, 2), prefer=1) == (0, 0)
    assert straight_subgoal(g, 3, 3, (0, 2), prefer=0) == (2, 2)


def test_the_field_is_built_off_the_tick_and_rebuilt_for_a_new_goal():
    work = Background(threaded=False)
    route = CellRoute(work)
    assert route.field(GRID, (4, 4)) is None and pending(work) == 1  # asked, not computed in the call
    assert route.field(GRID, (4, 4)) is None and pending(work) == 1  # asked once
    assert work.run_pending() == 1
    assert route.field(GRID, (4, 4)) == distance_field(GRID, (4, 4))
    assert route.field(GRID, (0, 0)) is None and pending(work) == 1  # another goal: another field
    work.run_pending()
    assert route.field(GRID, (0, 0)) == distance_field(GRID, (0, 0)) and route.builds == 2


def _driver() -> tuple[SectorMemoryDriver, Background]:
    work = Background(threaded=False)
    return SectorMemoryDriver(on_robot_map(load_policy(shipped_policy("sector_memory")), GRID), work), work


def _tick(x: int, y: int, heading: int, goal: tuple[int, int]) -> DriveTick:
    def vector(px: int, py: int) -> tuple[int, int]:
        import math

        return round(math.hypot(px - x, py - y)), round(1000 * math.atan2(py - y, px - x)) - heading

    return DriveTick(now_us=1_000_000, goal=goal, goal_index=0, drive_key=(goal, 0), pose_mm=(x, y, heading),
                     goal_bearing_mrad=vector(*goal)[1], ranges_mm=[2000] * N,
                     range_status=[robot_spec.RANGE_TOO_FAR] * N, goal_vector=vector)


def test_on_a_robot_with_a_map_the_bug_steps_toward_the_route_not_the_goal():
    """From (2, 4) facing north, the goal two cells east behind the wall: with the field there, the
    Bug's next cell is north (up the route), not east (through the wall its sensors read nothing of
    here); the sub-goal is the top of the column."""
    driver, work = _driver()
    start, goal = (2 * C + C // 2, C // 2), (4 * C + C // 2, C // 2)
    driver.next_step(_tick(*start, 1571, goal))  # the field is asked for; this decision steers on the goal
    work.run_pending()
    driver.open = None
    step = driver.next_step(_tick(*start, 1571, goal))
    assert driver.subgoal == (2, 0)
    assert not isinstance(step, str) and step.target == (start[0], start[1] + C)  # one cell north


def test_a_subgoal_not_reached_in_its_moves_hands_the_bug_back_the_goal():
    driver, work = _driver()
    start, goal = (2 * C + C // 2, C // 2), (4 * C + C // 2, C // 2)
    tick = _tick(*start, 1571, goal)
    driver.next_step(tick)
    work.run_pending()
    centre = start
    assert driver._steer_point(tick, centre, 1) == (2 * C + C // 2, 4 * C + C // 2)  # the sub-goal's centre
    budget = 2 * 4 + SUBGOAL_SLACK_MOVES
    for _ in range(budget):  # decisions that never get there (something the map does not show)
        assert driver._steer_point(tick, centre, 1) != goal
    assert driver._steer_point(tick, centre, 1) == goal and driver.subgoal is None
    assert driver._steer_point(tick, centre, 1) == goal  # for the rest of the drive


def test_without_a_map_the_bug_steers_on_the_goal():
    work = Background(threaded=False)
    pol = load_policy(shipped_policy("sector_memory"))
    from dataclasses import replace

    driver = SectorMemoryDriver(replace(pol, map_grid=None), work)
    goal = (4 * C + C // 2, C // 2)
    tick = _tick(2 * C + C // 2, C // 2, 1571, goal)
    assert driver._steer_point(tick, (tick.pose_mm[0], tick.pose_mm[1]), 1) == goal and pending(work) == 0
