"""The robot's re-planning when its local route is closed (`firmware_py.kinds.sector`): the obstacle
layer cleared by readings that see through a remembered point and pinned by a global re-plan, the
whole map's search finding another door (or none), and `PlannedTarget`'s recoveries in their order
(wait, global re-plan, back off, clear, "no route"), driven tick by tick on the controller clock."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

from firmware_py import robot_spec
from firmware_py.background import Background
from firmware_py.kinds.sector.config import LocalPlannerConfig
from firmware_py.kinds.sector.memory import MOVING_NEAR_MM, ObstacleMemory
from firmware_py.kinds.sector.planner import REFUGE_MM, LocalPlanner
from firmware_py.kinds.sector.recoveries import (
    BACKUP,
    GIVE_WAY,
    GLOBAL,
    LOCAL,
    NO_ROUTE,
    WAIT,
    PlannedTarget,
)
from firmware_py.mapdata import grid_from_rows
from tests.support.localplan_rig import CFG, FAR, INVALID, N, front

PERIOD = robot_spec.CONTROL_PERIOD_US
OPEN = grid_from_rows(["." * 10] * 10, 500)
# 10 x 7 cells of 500 mm: a wall along row 3 (y 1500..2000 mm) with a door at col 2 (x 1000..1500)
# and one at col 8 (x 4000..4500); TWO_DOORS has both, ONE_DOOR only the first
TWO_DOORS = grid_from_rows(["." * 10] * 3 + ["@@.@@@@@.@"] + ["." * 10] * 3, 500)
ONE_DOOR = grid_from_rows(["." * 10] * 3 + ["@@.@@@@@@@"] + ["." * 10] * 3, 500)
BELOW, ABOVE = (1250.0, 1000.0), (1250, 2600)
DOOR1 = [(1150, 1750), (1250, 1750), (1350, 1750)]
DOOR2 = [(4150, 1750), (4250, 1750), (4350, 1750)]


def _remember(memory: ObstacleMemory, points: list[tuple[int, int]], now_us: int = 0) -> None:
    """What `observe` stores for readings ending at these points (seen now)."""
    for x, y in points:
        key = (x // 50, y // 50)
        if key not in memory.points:
            memory.version += 1
            memory.added += 1
            memory.born[key] = now_us
        memory.points[key] = (x, y, now_us)


def test_a_reading_that_sees_through_a_remembered_point_clears_it():
    # robot at (1000, 1000) facing east: the front sensor's mount at x 1150, the point 500 mm ahead of it
    memory = ObstacleMemory(CFG)
    _remember(memory, [(1650, 1000)])
    ranges, status = front(600)  # an echo 100 mm behind the point: within the margin, the point stays
    memory.observe(OPEN, 1000, 1000, 0, ranges, status, 100_000)
    assert (1650 // 50, 1000 // 50) in memory.points
    v = memory.version
    ranges, status = front(1200)  # the cone reads 1.2 m: nothing at 0.5 m any more
    memory.observe(OPEN, 1000, 1000, 0, ranges, status, 200_000)
    assert (1650 // 50, 1000 // 50) not in memory.points and memory.version > v
    _remember(memory, [(1650, 1000)], 200_000)
    memory.observe(OPEN, 1000, 1000, 0, *front(0, FAR), 300_000)  # nothing within range: cleared too
    assert (1650 // 50, 1000 // 50) not in memory.points


def test_clearing_keeps_what_closed_the_route_out_there_and_counts_only_what_moves_near():
    """CLEAR (a recovery) forgets what is near the robot, but a point a global re-plan pinned that lies
    window_mm or more away is kept while pinned: a box seen from one side of the map, the robot gone
    round to meet it from the other side, forgetting it sent the robot round again and again instead
    of saying "no route" (the blocked bench's loops). `added` counts new points within MOVING_NEAR_MM
    of the robot only: a mover crossing the room in view, or walking to and fro a metre off a closed
    door, made every round a "moving scene"."""
    memory = ObstacleMemory(CFG)
    _remember(memory, [(1300, 1000), (1000 + CFG.window_mm + 200, 1000)])
    memory.pin(0)
    _remember(memory, [(1000, 1500 + CFG.window_mm)], 0)  # far but not pinned
    memory.clear(100_000, 1000, 1000, CFG.window_mm)
    assert set(memory.points) == {((1000 + CFG.window_mm + 200) // 50, 1000 // 50)}
    memory.clear(CFG.route_memory_us + 1, 1000, 1000, CFG.window_mm)  # its pin ran out
    assert not memory.points
    memory = ObstacleMemory(CFG)
    memory.observe(OPEN, 1000, 1000, 0, *front(CFG.window_mm + 300), 0)  # 1.45 m from the centre
    assert memory.points and memory.added == 0
    memory.observe(OPEN, 1000, 1000, 0, *front(MOVING_NEAR_MM), 50_000)  # 150 mm farther than that
    assert memory.added == 0
    memory.observe(OPEN, 1000, 1000, 0, *front(MOVING_NEAR_MM - 200), 100_000)
    assert memory.added == 1


def test_a_point_outside_every_cone_or_behind_an_invalid_reading_is_not_cleared():
    memory = ObstacleMemory(CFG)
    # 22 deg left of the nose (cones are 15 deg wide, 45 deg apart), and one ahead under an invalid reading
    off = (1000 + round(600 * math.cos(0.384)), 1000 + round(600 * math.sin(0.384)))
    _remember(memory, [off, (1650, 1000)])
    memory.observe(OPEN, 1000, 1000, 0, *front(0, INVALID), 100_000)
    assert set(memory.points) == {(off[0] // 50, off[1] // 50), (1650 // 50, 1000 // 50)}


def test_pinned_points_outlive_the_memory_but_not_a_reading_that_sees_through_them():
    memory = ObstacleMemory(CFG)
    _remember(memory, [(1650, 1000), (3000, 3000)])
    memory.pin(0)
    out_of_view = [2000] * N, [INVALID] * N
    memory.observe(OPEN, 1000, 1000, 0, *out_of_view, CFG.memory_us + 1)
    assert len(memory.points) == 2  # not seen for longer than memory_us, but pinned
    memory.observe(OPEN, 1000, 1000, 0, *front(0, FAR), CFG.memory_us + 2)  # nothing ahead
    assert set(memory.points) == {(3000 // 50, 3000 // 50)}
    memory.observe(OPEN, 1000, 1000, 0, *out_of_view, CFG.route_memory_us + 1)
    assert not memory.points  # the pin ran out


def test_the_window_is_blocked_and_the_whole_map_finds_the_other_door():
    memory = ObstacleMemory(CFG)
    _remember(memory, DOOR1)
    planner = LocalPlanner(TWO_DOORS, CFG)
    tx, ty = planner.target(*BELOW, ABOVE, memory)
    assert planner.blocked and not planner.no_route  # door 2 lies outside the window round door 1
    assert (tx, ty) == ABOVE
    planner.reset()
    tx, ty = planner.target(*BELOW, ABOVE, memory, whole_map=True)
    assert not planner.blocked and planner.detouring
    assert tx > BELOW[0] + 200 and ty < 1500  # along the wall toward door 2, not into door 1
    straight = math.hypot(ABOVE[0] - BELOW[0], ABOVE[1] - BELOW[1])
    assert planner.route_mm > straight + 5000  # the way round through door 2 (3 m across and back)


def test_no_door_left_is_no_route():
    memory = ObstacleMemory(CFG)
    _remember(memory, DOOR1 + DOOR2)
    planner = LocalPlanner(TWO_DOORS, CFG)
    planner.target(*BELOW, ABOVE, memory, whole_map=True)
    assert planner.blocked and planner.no_route
    memory = ObstacleMemory(CFG)
    _remember(memory, DOOR1)
    planner = LocalPlanner(ONE_DOOR, CFG)
    planner.target(*BELOW, ABOVE, memory, whole_map=True)
    assert planner.no_route


def _drive(pt: PlannedTarget, work: Background, memory: ObstacleMemory, ticks: int, t0: int = 0,
           seen: list[tuple[int, int]] | None = None) -> list[tuple[int, str, float, float, int, bool]]:
    """Ticks of the tick's side standing at BELOW, the search stepped between ticks (as the lockstep
    node does); `seen` re-remembered every tick (in view). Rows (t, mode, tx, ty, speed, reverse)."""
    rows = []
    for k in range(ticks):
        now = t0 + k * PERIOD
        if seen:
            _remember(memory, seen, now)
        tx, ty, speed = pt.target(now, *BELOW, ABOVE, memory)
        rows.append((now, pt.mode, tx, ty, speed, pt.reverse))
        work.run_pending()
    return rows


def test_recoveries_wait_then_re_plan_globally_and_follow_the_route():
    work = Background(threaded=False)
    memory = ObstacleMemory(CFG)
    _remember(memory, DOOR1)
    pt = PlannedTarget(TWO_DOORS, CFG, work)
    rows = _drive(pt, work, memory, 60)
    modes = [r[1] for r in rows]
    assert modes[0] == LOCAL and modes[1] == WAIT  # the first answer: blocked
    waited = [r for r in rows if r[1] == WAIT]
    assert all(r[4] == 0 for r in waited)  # standing still
    assert waited[-1][0] - waited[0][0] >= CFG.wait_us - PERIOD
    follow = [r for r in rows if r[1] == GLOBAL and r[4] > 0]
    assert follow and pt.global_plans == 1 and not pt.no_route
    assert follow[0][2] > BELOW[0] + 200 and follow[0][3] < 1500  # toward door 2
    assert memory.pinned  # the points that closed door 1 are kept while it goes round
    pt.reset()  # a new waypoint: local again
    assert pt.mode == LOCAL


def test_recoveries_back_off_clear_and_then_say_no_route():
    work = Background(threaded=False)
    memory = ObstacleMemory(CFG)
    pt = PlannedTarget(ONE_DOOR, CFG, work)
    rows = _drive(pt, work, memory, 400, seen=DOOR1)
    modes = [r[1] for r in rows]
    first_backup = modes.index(BACKUP)
    assert modes.index(WAIT) < modes.index(GLOBAL) < first_backup < modes.index(NO_ROUTE)
    backing = [r for r in rows if r[1] == BACKUP]
    assert any(r[5] for r in backing)  # the driver is told to reverse
    assert modes[first_backup:].count(WAIT) > 0  # after clearing: wait and re-plan again
    assert pt.no_route.startswith("no route to (1250,2600)") and len("mission item 99: " + pt.no_route) <= 50
    assert pt.global_plans == CFG.max_rounds
    assert all(r[4] == 0 for r in rows if r[1] == NO_ROUTE)
    # round r waits r x wait_us: 2 + 4 + 6 s of waiting, two back-offs, before "no route"
    said = rows[modes.index(NO_ROUTE)][0]
    assert 6 * CFG.wait_us + 2 * CFG.backoff_us <= said <= 6 * CFG.wait_us + 2 * CFG.backoff_us + 20 * PERIOD


def test_a_far_waypoint_behind_a_closed_door_waits_out_its_rounds_before_no_route():
    """A waypoint beyond max_plan_mm gets no window search: its answer is not the way opening, so
    each round after the first waits (r x wait_us) before the whole map is searched again. The wait
    ended at once: three rounds in about 2 s, and a mover in a maze corridor was "no route" (issue 47)."""
    far = (4750, 3250)  # across the wall of row 3, door 1 closed: no route
    assert math.hypot(far[0] - BELOW[0], far[1] - BELOW[1]) > CFG.max_plan_mm
    work = Background(threaded=False)
    memory = ObstacleMemory(CFG)
    pt = PlannedTarget(ONE_DOOR, CFG, work)
    modes = []
    for k in range(400):
        _remember(memory, DOOR1, k * PERIOD)
        pt.target(k * PERIOD, *BELOW, far, memory)
        modes.append(pt.mode)
        work.run_pending()
    said = modes.index(NO_ROUTE) * PERIOD
    # round 1 searches at once (a far waypoint behind a map wall); rounds 2 and 3 wait 4 + 6 s
    assert said >= 10 * CFG.wait_us // 2 + 2 * CFG.backoff_us and pt.global_plans == CFG.max_rounds


def test_a_mover_that_steps_aside_while_the_robot_waits_ends_the_recovery():
    work = Background(threaded=False)
    memory = ObstacleMemory(CFG)
    pt = PlannedTarget(TWO_DOORS, CFG, work)
    rows = _drive(pt, work, memory, 10, seen=DOOR1)
    assert rows[-1][1] == WAIT
    memory.clear()  # the readings saw through where it stood (what observe's clearing does)
    rows = _drive(pt, work, memory, 5, t0=10 * PERIOD)
    assert rows[-1][1] == LOCAL and rows[-1][4] == 100 and pt.global_plans == 0



def _no_route_with(moving: Callable[[int], list[tuple[int, int]]], static: list[tuple[int, int]]) -> tuple[int, int]:
    """When a robot standing at BELOW says "no route" (and after how many global searches) with the
    `static` points in view every tick and `moving(k)` the points a mover shows at tick k (the ones it
    showed the tick before are seen through: a new 50 mm square every tick)."""
    work = Background(threaded=False)
    memory = ObstacleMemory(CFG)
    pt = PlannedTarget(ONE_DOOR, CFG, work)
    for k in range(6000):  # the robot never moves here: each give-way ends when GIVE_WAY_US is out
        now = k * PERIOD
        for x, y in moving(k - 1):
            memory.points.pop((x // 50, y // 50), None)
        _remember(memory, static + moving(k), now)
        pt.target(now, *BELOW, ABOVE, memory)
        work.run_pending()
        if pt.mode == NO_ROUTE:
            return now, pt.global_plans
    return -1, pt.global_plans


def test_rounds_in_a_moving_scene_do_not_count_toward_no_route():
    # the only door held by a mover stepping to and fro in it (its body 50 mm further on or back
    # each tick): the robot keeps waiting and re-planning longer than for a still box
    said, plans = _no_route_with(lambda k: [(x, y + 50 * (k % 2)) for x, y in DOOR1], [])
    still = 6 * CFG.wait_us + 2 * CFG.backoff_us  # when a still box is declared (test above)
    assert said > 2 * still and plans == 3 * CFG.max_rounds


def test_a_person_shifting_on_the_spot_in_the_door_is_a_moving_scene():
    # the standard bench's movers stop for the robot: one standing in the only door since before the
    # wait, shifting 50 mm now and then, shows a few new points beside its old ones; the old ones are
    # the same body (within BODY_MM of a new one), so the way is not closed by what stands still
    def shifting(k: int) -> list[tuple[int, int]]:
        return [(x, y + 50 * ((k // 10) % 2)) for x, y in DOOR1[:1]]

    said, plans = _no_route_with(shifting, DOOR1[1:])
    still = 6 * CFG.wait_us + 2 * CFG.backoff_us  # when a still box is declared (test above)
    assert said > 2 * still and plans == 3 * CFG.max_rounds


def test_a_mover_walking_past_near_the_robot_does_not_hold_open_a_door_a_box_closes():
    """The blocked bench's last loop (trap, seed 0): a box closes the only door and a mover walks to
    and fro 0.3-0.5 m beside the waiting robot. New points near it made every round a moving scene
    and the robot searched on; what moved did not close the way, so the rounds count."""
    def beside(k: int) -> list[tuple[int, int]]:
        return [(int(BELOW[0]) - 450 + 50 * (k % 8), int(BELOW[1]) - 300)]

    assert all(math.hypot(x - BELOW[0], y - BELOW[1]) < MOVING_NEAR_MM for k in range(8) for x, y in beside(k))
    said, plans = _no_route_with(beside, DOOR1)
    still = 6 * CFG.wait_us + 2 * CFG.backoff_us  # when a still box is declared (test above)
    assert still <= said <= still + 20 * PERIOD and plans == CFG.max_rounds


def test_rounds_in_which_something_came_up_to_the_robot_do_not_count_toward_no_route():
    """A person who will not give way walked up to the robot in the only door and stands there (a
    still scene: no new points while the robot waits). The robot never drives that close itself (the
    guard vetoes a step ahead under veto_mm), so a remembered point within its radius + veto_mm came
    to it: a moving scene, rounds not counted (the cap of 3 x max_rounds still ends it); a box the
    robot stopped short of is declared as before."""
    def said(gap_mm: int) -> tuple[int, int]:
        work = Background(threaded=False)
        memory = ObstacleMemory(CFG)
        pt = PlannedTarget(ONE_DOOR, CFG, work)
        person = (int(BELOW[0]), int(BELOW[1]) + robot_spec.ROBOT_RADIUS_MM + gap_mm)
        for k in range(6000):  # the robot never moves here: each give-way ends when GIVE_WAY_US is out
            now = k * PERIOD
            if pt.mode != BACKUP:  # seen again after each CLEAR: it stands where it stood
                _remember(memory, DOOR1 + [person], now)
            pt.target(now, *BELOW, ABOVE, memory)
            work.run_pending()
            if pt.mode == NO_ROUTE:
                return now, pt.global_plans
        return -1, pt.global_plans

    still = 6 * CFG.wait_us + 2 * CFG.backoff_us  # when a still box is declared (test above)
    at_box, plans = said(CFG.veto_mm + 10)
    assert still <= at_box <= still + 20 * PERIOD and plans == CFG.max_rounds
    at_person, plans = said(CFG.veto_mm - 20)
    assert at_person > 2 * still and plans == 3 * CFG.max_rounds


def test_what_walked_into_the_only_other_door_is_approached_before_the_round_counts():
    """A box closes door 1 from the start; a person walks into door 2 during the round's wait and
    stands there (a few new points: not a moving scene by their count). The whole map has no route,
    but it has one without what came in during the wait: the robot drives it toward door 2 for
    approach_us from the search (the person walks on or steps aside as it comes; readings see through
    where it stood), then, the way still closed, goes on with the round (backs off). It backs off at
    once where door 2 was closed before the wait, where only a box's readings jitter, and where a
    person walks up beside the box that closes door 2 (what closes the way was there before)."""
    def rows_with(cfg: LocalPlannerConfig, before: list[tuple[int, int]],
                  late: list[tuple[int, int]]) -> list[tuple[int, str, float, float, int, bool]]:
        """The ticks up to the first BACKUP; `late` in view from tick 5 (the wait began at tick 1)."""
        work = Background(threaded=False)
        memory = ObstacleMemory(cfg)
        pt = PlannedTarget(TWO_DOORS, cfg, work)
        rows = _drive(pt, work, memory, 5, seen=DOOR1 + before)
        rows += _drive(pt, work, memory, 395, t0=5 * PERIOD, seen=DOOR1 + before + late)
        return rows[:next(i for i, r in enumerate(rows) if r[1] == BACKUP) + 1]

    rows = rows_with(CFG, [], DOOR2)
    searched = next(r[0] for r in rows if r[1] == GLOBAL)
    driving = [r for r in rows if r[1] == GLOBAL and r[4] > 0]
    assert driving and all(r[2] > BELOW[0] + 200 and r[3] < 1750 for r in driving)  # toward door 2
    backed = next(r[0] for r in rows if r[1] == BACKUP)
    assert CFG.approach_us <= backed - searched <= CFG.approach_us + 3 * PERIOD
    jitter = [(x + 25, y + 50) for x, y in DOOR2]  # new 50 mm squares beside the box's
    walk_up = [(4250, 2350), (4250, 2150), (4250, 1950)]  # a person from 600 mm above door 2 to its edge
    for cfg, before, late in ((replace(CFG, approach_us=1), [], DOOR2), (CFG, DOOR2, []), (CFG, DOOR2, jitter),
                              (CFG, DOOR2, walk_up)):
        rows = rows_with(cfg, before, late)
        assert rows[-1][1] == BACKUP and not [r for r in rows if r[1] == GLOBAL and r[4] > 0], (before, late)
        assert rows[-1][0] - next(r[0] for r in rows if r[1] == GLOBAL) <= 3 * PERIOD


def test_a_far_waypoint_behind_a_map_wall_is_reached_by_the_whole_map_route():
    """A waypoint beyond max_plan_mm is driven at without planning while the map leaves the line to
    it free; once a detour has taken the robot where the map's walls stand between (a maze: a straight
    drive stalls at the first wall) the tick's side switches to the whole map's route (the sight line
    is looked at off the tick)."""
    far = (4750, 3000)  # 4 m from BELOW, across the wall of row 3
    assert math.hypot(far[0] - BELOW[0], far[1] - BELOW[1]) > CFG.max_plan_mm
    for grid, walled in ((TWO_DOORS, True), (OPEN, False)):
        work = Background(threaded=False)
        memory = ObstacleMemory(CFG)
        pt = PlannedTarget(grid, CFG, work)
        rows = []
        for k in range(6):
            tx, ty, speed = pt.target(k * PERIOD, *BELOW, far, memory)
            rows.append((pt.mode, (tx, ty), speed))
            work.run_pending()
        assert rows[0] == (LOCAL, far, 100)  # the first tick: the sight line is being looked at
        if walled:
            assert rows[1][0] == GLOBAL and rows[1][2] == 0 and pt.global_plans == 1
            follow = [r for r in rows if r[0] == GLOBAL and r[2] > 0]
            assert follow and follow[-1][1] != far  # on the route, toward a door
        else:
            assert all(r == (LOCAL, far, 100) for r in rows) and pt.global_plans == 0


def test_a_route_squeezed_between_points_leads_on_not_to_the_robots_own_cell():
    """Remembered points either side of the way, nearer than los_clear_mm but farther than
    obstacle_clear_mm: the route is open but none of its cells is in plain sight. The target is the
    route's next cell (as a window's detour takes it); steering to the robot's own cell held it there."""
    memory = ObstacleMemory(CFG)
    off = (CFG.obstacle_clear_mm + CFG.los_clear_mm) // 2
    _remember(memory, [(x, y) for y in range(700, 2400, 50) for x in (1025 - off, 1025 + off)])
    planner = LocalPlanner(OPEN, CFG)
    tx, ty = planner.target(1025, 1025, (1025, 2025), memory, whole_map=True)
    assert not planner.blocked and planner.detouring
    assert ty >= 1025 + CFG.raster_mm  # a cell on, up the way


def test_a_route_closed_ahead_is_held_to_a_while_before_the_whole_map_is_searched_again():
    """On the whole map's route round door 2, points across the way ahead (a mover walking over it):
    the robot stands and the planner holds to the route for wait_us; if they clear meanwhile it drives
    on along the same route (no new search), else the search runs again after wait_us. A mover had
    sent the robot between two doors and back for good."""
    across = [(2000, y) for y in range(50, 1500, 50)]  # the corridor below the wall, 750 mm east
    for clears in (True, False):
        work = Background(threaded=False)
        memory = ObstacleMemory(CFG)
        _remember(memory, DOOR1)
        pt = PlannedTarget(TWO_DOORS, CFG, work)
        rows = _drive(pt, work, memory, 60)
        assert rows[-1][1] == GLOBAL and rows[-1][4] > 0  # on the route to door 2
        plans, t0, route = pt.plans, 60 * PERIOD, pt.route_mm
        _remember(memory, across, t0)
        hold = CFG.wait_us // PERIOD
        rows = _drive(pt, work, memory, hold // 2, t0=t0)
        assert all(r[4] == 0 for r in rows[1:]) and pt.plans == plans  # standing, the route kept
        # ... and its length with it (benchmarks measure progress on it; the straight line to the
        # waypoint, 1.6 m, had given a tick of false progress)
        assert pt.route_mm == route > math.hypot(ABOVE[0] - BELOW[0], ABOVE[1] - BELOW[1]) + 1000
        if clears:
            for x, y in across:  # seen through: gone
                memory.points.pop((x // 50, y // 50))
            memory.version += 1
            rows = _drive(pt, work, memory, 5, t0=t0 + (hold // 2) * PERIOD)
            assert rows[-1][1] == GLOBAL and rows[-1][4] > 0 and pt.plans == plans
        else:
            rows = _drive(pt, work, memory, hold, t0=t0 + (hold // 2) * PERIOD)
            assert pt.plans > plans  # searched again once the hold ran out


def test_another_way_round_after_the_route_closed_counts_as_a_new_route():
    """Doors at columns 2, 5 and 8; door 1 closed: the route goes through door 5 (one route taken).
    Door 5 closes too: after the hold the search finds the way through door 8, longer by more than
    ROUTE_SWITCH_MM, and that counts as a route taken (benchmarks measure progress along it anew)."""
    from firmware_py.kinds.sector.recoveries import ROUTE_SWITCH_MM

    three = grid_from_rows(["." * 10] * 3 + ["@@.@@.@@.@"] + ["." * 10] * 3, 500)
    work = Background(threaded=False)
    memory = ObstacleMemory(CFG)
    _remember(memory, DOOR1)
    pt = PlannedTarget(three, CFG, work)
    rows = _drive(pt, work, memory, 60)
    assert rows[-1][1] == GLOBAL and rows[-1][4] > 0 and pt.routes_taken == 1
    before = pt.route_mm
    _remember(memory, [(2650, 1750), (2750, 1750), (2850, 1750)], 60 * PERIOD)  # door 5
    rows = _drive(pt, work, memory, CFG.wait_us // PERIOD + 10, t0=60 * PERIOD)
    held = [r for r in rows if r[4] == 0]
    assert len(held) >= CFG.wait_us // PERIOD - 2  # the hold first
    assert rows[-1][1] == GLOBAL and rows[-1][4] > 0  # then on, the way through door 8
    assert pt.route_mm > before + ROUTE_SWITCH_MM and pt.routes_taken == 2
    _drive(pt, work, memory, 20, t0=(60 + len(rows)) * PERIOD)
    assert pt.routes_taken == 2  # following it is not another route


# 10 x 5 cells of 500 mm: a one-cell corridor along row 3 (y 500..1000 mm) with a side corridor north at
# col 4 (x 2000..2500, y 1000..2000); NO_SIDE without it
SIDE = grid_from_rows(["@" * 10, "@@@@.@@@@@", "@@@@.@@@@@", "." * 10, "@" * 10], 500)
NO_SIDE = grid_from_rows(["@" * 10] * 3 + ["." * 10, "@" * 10], 500)
IN_SIDE = (2000 + 175, 2500 - 175)  # the side corridor's x range the robot's centre can take


def _person(x: int, y: int = 750) -> list[tuple[int, int]]:
    """What the robot remembers of a person standing with their near side at x (a 100 mm arc)."""
    return [(x, y - 50), (x, y), (x, y + 50)]


def test_the_refuge_is_the_side_corridor_behind_the_robot_off_the_line_the_person_walks():
    memory = ObstacleMemory(CFG)
    _remember(memory, _person(2780))  # east of the robot, at it
    refuge = LocalPlanner(SIDE, CFG).refuge(2600, 750, memory)
    assert refuge is not None and IN_SIDE[0] <= refuge[0] <= IN_SIDE[1] and refuge[1] >= 750 + REFUGE_MM
    # a person a little off the corridor's middle (the line robot -> person 27 deg off the axis): the line
    # is taken along the corridor, and the refuge is still the side corridor
    memory = ObstacleMemory(CFG)
    _remember(memory, _person(2780, 850))
    refuge = LocalPlanner(SIDE, CFG).refuge(2600, 750, memory)
    assert refuge is not None and IN_SIDE[0] <= refuge[0] <= IN_SIDE[1] and refuge[1] >= 750 + REFUGE_MM
    # the person stands between the robot and the side corridor, or there is none: nowhere to stand aside
    memory = ObstacleMemory(CFG)
    _remember(memory, _person(2620))
    assert LocalPlanner(SIDE, CFG).refuge(2800, 750, memory) is None
    memory = ObstacleMemory(CFG)
    _remember(memory, _person(2780))
    assert LocalPlanner(NO_SIDE, CFG).refuge(2600, 750, memory) is None
    assert LocalPlanner(SIDE, CFG).refuge(2600, 750, ObstacleMemory(CFG)) is None


# SIDE's corridor 20 cells long: the side corridor at col 4, 4 m behind a robot at x 6600
FAR_SIDE = grid_from_rows(["@" * 20, "@@@@.@@@@@@@@@@@@@@@", "@@@@.@@@@@@@@@@@@@@@", "." * 20, "@" * 20], 500)


def test_a_side_corridor_metres_back_is_a_refuge():
    # in a maze a person walking the one-cell corridor the robot is in is met metres from the junction it
    # came through; backing off there and standing aside lets the person pass (the oracle of `qnav bench
    # ceiling` waits off the line at such junctions: docs/results.md 6.1)
    memory = ObstacleMemory(CFG)
    _remember(memory, _person(6780))
    refuge = LocalPlanner(FAR_SIDE, CFG).refuge(6600, 750, memory)
    assert refuge is not None and IN_SIDE[0] <= refuge[0] <= IN_SIDE[1] and refuge[1] >= 750 + REFUGE_MM
    memory = ObstacleMemory(CFG)
    _remember(memory, _person(7980))
    assert LocalPlanner(FAR_SIDE, CFG).refuge(7800, 750, memory) is None  # 5.5 m back: beyond REFUGE_SEARCH_MM


def test_a_person_who_will_not_give_way_is_stood_aside_for_and_the_waypoint_reached_after():
    """A person walks at the robot down the one-cell corridor and stands at it (they stop only on
    contact). The robot drives into the side corridor behind it and stands there; once the person has
    walked past (the points gone) it goes back to the route by the whole map's search and reaches the
    waypoint. A point robot steps 20 mm a tick toward the target it is given."""
    work = Background(threaded=False)
    memory = ObstacleMemory(CFG)
    pt = PlannedTarget(SIDE, CFG, work)
    x, y = 2600.0, 750.0
    waypoint = (4250, 750)
    modes, deepest, gone_at = [], 0.0, None
    for k in range(3000):
        now = k * PERIOD
        if gone_at is None:
            # the person follows the robot along the corridor while it is in the corridor (y < 1000)
            _remember(memory, _person(round(x) + robot_spec.ROBOT_RADIUS_MM + 30) if y < 1000 else [], now)
            if y >= 1000 and pt.mode == WAIT:
                gone_at = now  # the robot stands aside: the person walks past
                memory.clear()
        tx, ty, speed = pt.target(now, x, y, waypoint, memory)
        modes.append(pt.mode)
        if speed:
            d = math.hypot(tx - x, ty - y)
            step = min(20.0, d)
            if d > 0:
                x, y = x + step * (tx - x) / d, y + step * (ty - y) / d
        deepest = max(deepest, y)
        work.run_pending()
        if math.hypot(waypoint[0] - x, waypoint[1] - y) < 100:
            break
    assert GIVE_WAY in modes and pt.give_ways == 1 and NO_ROUTE not in modes and BACKUP not in modes
    assert deepest >= 750 + REFUGE_MM - 100  # it stood in the side corridor
    assert gone_at is not None and math.hypot(waypoint[0] - x, waypoint[1] - y) < 100  # then reached it
    assert GLOBAL in modes[modes.index(GIVE_WAY):]  # back by the whole map's route


def test_with_nowhere_to_stand_aside_the_robot_backs_off_as_in_a_still_scene():
    work = Background(threaded=False)
    memory = ObstacleMemory(CFG)
    pt = PlannedTarget(NO_SIDE, CFG, work)
    modes = []
    for k in range(200):
        now = k * PERIOD
        if pt.mode != BACKUP:
            _remember(memory, _person(2600 + robot_spec.ROBOT_RADIUS_MM + 30), now)
        pt.target(now, 2600.0, 750.0, (4250, 750), memory)
        modes.append(pt.mode)
        work.run_pending()
    assert BACKUP in modes and GIVE_WAY not in modes
