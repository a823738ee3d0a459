"""The robot's local planner (`firmware_py.kinds.sector`): which readings the
map explains (a map wall, also from a pose a little off, the border and a
grazed corner) and which it does not (a disc in the open), its parameters as
policy metadata (checked at load), the obstacle memory (unmapped end points
only, forgotten on the controller clock) and the sub-goals (the waypoint
while nothing is in the way, a point beside an obstacle across the line,
the waypoint again after `reset` with the way clear), and the controller
steering a sector policy on them."""

from __future__ import annotations

import math
import random
from array import array

import pytest

from firmware_py import robot_spec
from firmware_py.control.controller import Controller
from firmware_py.kinds.sector.config import META_KEY, LocalPlannerConfig
from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.kinds.sector.memory import ObstacleMemory
from firmware_py.kinds.sector.planner import LocalPlanner
from firmware_py.mapdata import grid_from_rows, unmapped_readings, wall_within
from firmware_py.policy import PolicyError, dump_policy, load_policy
from firmware_py.vehicle import VehicleConfig
from tests.support.background import pending
from tests.support.controller_rig import SECTOR_TRAINING_MAP, Kinematic, Rig
from tests.support.localplan_rig import CFG, CLOSE, FAR, N, V, front

OPEN = ["." * 10] * 10
WALL = ["." * 3 + "@" + "." * 6] * 10  # column 3: x 1500..2000 mm

# 6 x 5 cells of 500 mm, a wall column at col 4 (x 2000..2500 mm) with the map's border around
GRID = grid_from_rows(["......", "....@.", "....@.", "....@.", "......"], 500)


def test_a_map_wall_is_explained_a_disc_in_the_open_is_not():
    # robot at x 1500 facing east (heading 0): front sensor's mount at x 1650, the wall's face at x 2000
    ranges = [350] + [2000] * 7
    status = [V] + [FAR] * 7
    assert unmapped_readings(GRID, 1500, 1250, 0, ranges, status, 150)[0] == -1
    # the same reading 100 mm off in x (the localiser's corridor error) is still the wall
    assert unmapped_readings(GRID, 1400, 1250, 0, ranges, status, 150)[0] == -1
    # a reading of 200 mm ends 150 mm short of the wall (within the margin); 190 mm ends 160 short: a disc
    ranges[0] = 200
    assert unmapped_readings(GRID, 1500, 1250, 0, ranges, status, 150)[0] == -1
    ranges[0] = 190
    assert unmapped_readings(GRID, 1500, 1250, 0, ranges, status, 150)[0] == 190
    # too far never counts; too close in the open is an unmapped contact (distance 0)
    assert unmapped_readings(GRID, 1500, 1250, 0, [20] + [2000] * 7, [CLOSE] + [FAR] * 7, 150)[0] == 0
    assert all(d == -1 for d in unmapped_readings(GRID, 1500, 1250, 0, [2000] * 8, [FAR] * 8, 150))


def test_wall_within_is_the_distance_to_the_nearest_wall_square():
    """`wall_within` (every reading's three rays ask it each tick) against the distance to each
    occupied cell's square and to the world outside the grid, brute force, at points in, on the
    edge of and outside the grid, for margins from 1 mm to two cells."""
    rng = random.Random(7)
    rows = ["".join("@" if rng.random() < 0.25 else "." for _ in range(7)) for _ in range(6)]
    grid = grid_from_rows(rows, 500)
    width, height = 7 * 500, 6 * 500

    def gap(x: int, y: int) -> float:
        if not (0 < x < width and 0 < y < height):
            return 0.0
        best = float(min(x, y, width - x, height - y))  # the outside is wall
        for row, line in enumerate(rows):
            for col, ch in enumerate(line):
                if ch == "@":
                    xlo, ylo = col * 500, height - (row + 1) * 500
                    best = min(best, math.hypot(max(xlo - x, 0, x - xlo - 500), max(ylo - y, 0, y - ylo - 500)))
        return best

    points = [(rng.randrange(-300, width + 300), rng.randrange(-300, height + 300)) for _ in range(400)]
    points += [(500, 1000), (1000, 1000), (width, 250), (0, 0)]  # on cell corners and the border
    for m in (1, 150, 499, 500, 1000):
        for x, y in points:
            assert wall_within(grid, x, y, m) == (gap(x, y) <= m), (x, y, m, gap(x, y))


def test_the_outer_border_and_a_grazed_corner_are_explained():
    # facing north from (750, 2000): the border (y 2500) 500 - 150 = 350 mm from the front sensor
    um = unmapped_readings(GRID, 750, 2000, 1571, [350] + [0] * 7, [V] + [FAR] * 7, 150)
    assert um[0] == -1
    # heading at the wall block's south-west corner (2000, 1000) from (1600, 700): a reading ending at the corner
    um = unmapped_readings(GRID, 1600, 700, 644, [350] + [0] * 7, [V] + [FAR] * 7, 150)
    assert um[0] == -1


def test_config_round_trips_and_bad_fields_are_named():
    assert LocalPlannerConfig.from_metadata(CFG.to_metadata()) == CFG
    assert LocalPlannerConfig.from_metadata({}) == CFG
    assert LocalPlannerConfig.from_metadata({"memory_us": 500_000}).memory_us == 500_000
    for bad, what in (([], "not a JSON object"), ({"speed": 1}, "unknown field 'speed'"),
                      ({"raster_mm": 0}, "raster_mm = 0"), ({"weight": True}, "weight = True"),
                      ({"memory_us": 1.5}, "memory_us = 1.5"), ({"raster_mm": 20}, "allowed 50..500"),
                      ({"wall_clear_mm": 5000}, "wall_clear_mm = 5000"), ({"lookahead_mm": 9000}, "lookahead_mm <= 5000"),
                      ({"los_clear_mm": 100}, "obstacle_clear_mm <= los_clear_mm <= soft_mm"),
                      ({"max_points": 2000}, "max_points <= 1000"),
                      ({"raster_mm": 50}, "more than 5 raster cells"),
                      ({"raster_mm": 50, "soft_mm": 250, "los_clear_mm": 200, "window_mm": 5000},
                       "search window is 260 raster cells a side")):
        with pytest.raises(ValueError, match=what):
            LocalPlannerConfig.from_metadata(bad)


def test_memory_keeps_unmapped_end_points_and_forgets_them_on_the_clock():
    mem = ObstacleMemory(CFG)
    ranges, status = front(300)  # front sensor at x 1150 + 300: x 1450 in the open
    mem.observe(grid_from_rows(OPEN, 500), 1000, 2250, 0, ranges, status, 0)
    assert len(mem.points) == 1 and mem.version == 1
    (x, y, t), = mem.points.values()
    assert (x, y, t) == (1450, 2250, 0)
    mem.observe(grid_from_rows(OPEN, 500), 1000, 2250, 0, ranges, status, 2_000_000)  # seen again: no new version
    assert mem.version == 1 and next(iter(mem.points.values()))[2] == 2_000_000
    far, fstat = front(2000)
    mem.observe(grid_from_rows(OPEN, 500), 1000, 2250, 0, far, [FAR] * N, 2_000_000 + CFG.memory_us + 1)
    assert not mem.points and mem.version == 2  # forgotten
    walled = ObstacleMemory(CFG)
    walled.observe(grid_from_rows(WALL, 500), 1000, 2250, 0, *front(350), 0)  # ends on the wall's face
    assert not walled.points
    beyond = ObstacleMemory(CFG)
    beyond.observe(grid_from_rows(OPEN, 500), 1000, 2250, 0, *front(CFG.see_mm + 1), 0)
    assert not beyond.points


def _disc_points(cx: int, cy: int, r: int) -> ObstacleMemory:
    mem = ObstacleMemory(CFG)
    for k in range(12):  # the side of a disc facing the robot, as readings would leave it
        a = math.pi / 2 + k * math.pi / 11
        x, y = round(cx + r * math.cos(a)), round(cy + r * math.sin(a))
        mem.points[(x // 50, y // 50)] = (x, y, 0)
    mem.version += 1
    return mem


def test_sub_goal_goes_round_an_obstacle_across_the_line_only():
    grid = grid_from_rows(OPEN, 500)
    planner = LocalPlanner(grid, CFG)
    empty = ObstacleMemory(CFG)
    assert planner.target(1250, 2500, (3750, 2500), empty) == (3750.0, 2500.0) and not planner.detouring
    mem = _disc_points(2500, 2500, 150)  # across the straight line
    tx, ty = planner.target(1250, 2500, (3750, 2500), mem)
    assert planner.detouring and planner.plans == 1
    assert abs(ty - 2500) > 200  # beside the disc, not through it
    # every point of the line to the target keeps the obstacle clearance from the remembered points
    for f in (i / 20 for i in range(21)):
        px, py = 1250 + f * (tx - 1250), 2500 + f * (ty - 2500)
        assert min(math.hypot(px - x, py - y) for x, y, _ in mem.points.values()) >= CFG.obstacle_clear_mm
    planner.target(1260, 2500, (3750, 2500), mem)
    assert planner.plans == 1  # same memory, same waypoint: the plan is reused
    far = LocalPlanner(grid_from_rows(["." * 20] * 10, 500), CFG)
    assert far.target(1250, 2500, (1250 + CFG.max_plan_mm + 100, 2500), mem) == (1250.0 + CFG.max_plan_mm + 100, 2500.0)
    assert far.plans == 0 and not far.detouring  # too far to plan: straight at it (bounded work per tick)
    side = _disc_points(2500, 3500, 150)  # 1 m beside the line: not in the way
    planner.reset()
    assert planner.target(1250, 2500, (3750, 2500), side) == (3750.0, 2500.0) and not planner.detouring


def test_sub_goal_stays_out_of_map_walls():
    rows = ["." * 10] * 4 + ["...@@@@..."] + ["." * 10] * 5  # a wall row at y 2500..3000, x 1500..3500
    planner = LocalPlanner(grid_from_rows(rows, 500), CFG)
    mem = _disc_points(2500, 1800, 150)  # a disc below the wall, on the line
    tx, ty = planner.target(1000, 1800, (4000, 1800), mem)
    assert planner.detouring and ty < 1800  # round the open side, not into the wall
    assert not planner._open_map((25, 27)) and planner._open_map((25, 18))  # the wall's raster cells are closed


def _policy(meta: dict) -> bytes:
    enc = SectorEncoder(15, (0, 1, 7), (100, 400))
    vals = array("b")
    for s in range(enc.n_states):  # forward when the target is in the sector ahead, else turn toward it
        b = s // 27
        a = 0 if b == 0 else (1 if b <= 7 else 2)
        vals.extend(100 if i == a else 0 for i in range(4))
    return dump_policy(enc, vals, "int8", 0.01, map_geometry=SECTOR_TRAINING_MAP, metadata=meta)


def test_the_search_runs_off_the_tick_and_the_robot_slows_then_stops_without_an_answer():
    from firmware_py.background import Background
    from firmware_py.kinds.sector.recoveries import PLAN_SLOW_US, PLAN_STOP_US, PlannedTarget
    work = Background(threaded=False)
    planned = PlannedTarget(grid_from_rows(OPEN, 500), CFG, work)
    mem = _disc_points(2500, 2500, 150)  # across the line to the waypoint
    assert planned.target(0, 1250, 2500, (3750, 2500), ObstacleMemory(CFG)) == (3750.0, 2500.0, 100)
    assert pending(work) == 0  # nothing in the way: nothing asked
    assert planned.target(0, 1250, 2500, (3750, 2500), mem) == (3750.0, 2500.0, 100)  # blocked just now
    assert planned.plans == 0 and pending(work) == 1  # the question is queued, the tick did not search
    speeds = [planned.target(t, 1250, 2500, (3750, 2500), mem)[2]
              for t in (PLAN_SLOW_US, PLAN_SLOW_US + 1, PLAN_STOP_US, PLAN_STOP_US + 1)]
    assert speeds == [100, 50, 50, 0] and planned.plans == 0  # no answer: slower, then stopped
    assert work.run_pending() == 1 and planned.plans == 1  # latest question only
    tx, ty, speed = planned.target(PLAN_STOP_US + 2, 1250, 2500, (3750, 2500), mem)
    assert speed == 100 and planned.detouring and abs(ty - 2500) > 200  # answered: round the disc, full speed
    planned.reset()  # a new waypoint: an answer for the old one is never used
    assert planned.target(PLAN_STOP_US + 3, 1250, 2500, (3750, 2600), mem)[:2] == (3750.0, 2600.0)
    assert not planned.detouring


def test_background_runs_the_latest_job_per_owner_and_keeps_errors_out_of_the_caller():
    import threading

    from firmware_py.background import Background
    stepped = Background(threaded=False)
    ran: list[str] = []
    owner_a, owner_b = object(), object()
    stepped.post(owner_a, lambda: ran.append("a1"))
    stepped.post(owner_a, lambda: ran.append("a2"))  # replaces a1, not started
    stepped.post(owner_b, lambda: 1 / 0)
    assert ran == [] and pending(stepped) == 2
    assert stepped.run_pending() == 2 and ran == ["a2"] and stepped.errors == 1 and stepped.runs == 2
    threaded = Background(threaded=True)
    done = threading.Event()
    threaded.post(owner_a, lambda: 1 / 0)
    threaded.post(owner_b, lambda: done.set() if threading.current_thread().name == "qnav-background" else None)
    assert done.wait(5.0) and threaded.errors == 1  # the worker survives a failing job
    threaded.close()
    threaded.post(owner_a, lambda: ran.append("after close"))
    assert pending(threaded) == 0 and ran == ["a2"]


def test_policy_metadata_is_checked_at_load():
    pol = load_policy(_policy({"map_grid": OPEN, META_KEY: {"memory_us": 1_000_000}}))
    assert pol.kind_config == LocalPlannerConfig(memory_us=1_000_000)
    assert load_policy(_policy({"map_grid": OPEN})).kind_config is None
    with pytest.raises(PolicyError, match="needs a plain sector policy that carries its map"):
        load_policy(_policy({META_KEY: {}}))
    with pytest.raises(PolicyError, match="local_planner.weight = -1"):
        load_policy(_policy({"map_grid": OPEN, META_KEY: {"weight": -1}}))


def test_controller_steers_on_the_sub_goal_and_resets_per_goal():
    pol = load_policy(_policy({"map_grid": OPEN, META_KEY: {}}))
    # lockstep: the planner's search runs when the node calls background.run_pending() between ticks
    ctrl = Controller(VehicleConfig(), pol, start_pose_mm=(1000, 2250, 0), localise=False, lockstep=True)
    rig = Rig(ctrl, Kinematic(1000, 2250, 0))
    rig.tick()
    assert ctrl.arm() == (True, "")
    assert ctrl.go_to(3750, 2250) == (True, "")
    rig.tick(ranges_mm=[2000] * N, range_status=[FAR] * N)
    assert ctrl.target_mm is None and rig.last_motor.left_mm_s == rig.last_motor.right_mm_s > 0  # straight on
    fr, fs = front(400)
    rig.tick(ranges_mm=fr, range_status=fs)  # something the map does not show 400 mm ahead
    planner = ctrl.driver.local[0]  # type: ignore[union-attr]
    assert ctrl.target_mm is None and planner.plans == 0  # asked, not searched in the tick
    assert ctrl.background.run_pending() == 1 and planner.plans == 1  # between ticks, as the node does
    rig.tick(ranges_mm=fr, range_status=fs)
    assert ctrl.target_mm is not None and abs(ctrl.target_mm[1] - 2250) > 100
    assert rig.last_motor.left_mm_s != rig.last_motor.right_mm_s  # turning toward the side-step
    assert ctrl.go_to(1000, 4250) == (True, "")
    rig.tick(ranges_mm=[2000] * N, range_status=[FAR] * N)
    assert ctrl.target_mm is None  # a new goal with a clear way: the goal itself


def test_localiser_does_not_weigh_readings_of_unmapped_obstacles():
    rows = WALL  # a wall column at x 1500..2000 mm
    pol = load_policy(_policy({"map_grid": rows, META_KEY: {}}))
    ctrl = Controller(VehicleConfig(), pol, start_pose_mm=(1000, 2250, 0))
    assert ctrl.loc is not None and ctrl.loc.localised  # started at a known pose: tracking
    rig = Rig(ctrl, Kinematic(1000, 2250, 0))
    out = rig.tick()
    assert out is not None
    fr, fs = front(150)  # ends at x 1300, 200 mm short of the wall: nothing on the map there
    inp = rig.inp
    inp.ranges_mm, inp.range_status = fr, fs
    assert ctrl.pose.statuses(inp, ctrl.kind.localiser_margin_mm)[0] == robot_spec.RANGE_INVALID
    inp.ranges_mm, inp.range_status = front(350)  # ends on the wall's face
    assert ctrl.pose.statuses(inp, ctrl.kind.localiser_margin_mm)[0] == V
    plain = Controller(VehicleConfig(), load_policy(_policy({"map_grid": rows})), start_pose_mm=(1000, 2250, 0))
    inp.ranges_mm, inp.range_status = fr, fs
    assert plain.pose.statuses(inp, plain.kind.localiser_margin_mm)[0] == V  # without a planner the localiser sees everything


def _guard_inputs(front: int = 2000, rear: int = 2000, rear_sides: int = 2000) -> tuple[list[int], list[int]]:
    ranges = [2000] * N
    ranges[0], ranges[4], ranges[3], ranges[5] = front, rear, rear_sides, rear_sides
    return ranges, [V if r < 2000 else FAR for r in ranges]


def test_guard_vetoes_a_forward_step_into_a_near_reading():
    from firmware_py.kinds.sector.guard import FORWARD, TURN_LEFT, TURN_RIGHT, MotionGuard

    guard, mem = MotionGuard(CFG), ObstacleMemory(CFG)
    assert guard.action(0, 0, 0, FORWARD, 300, *_guard_inputs(front=CFG.veto_mm + 1), mem) == FORWARD
    assert guard.action(50_000, 0, 0, FORWARD, 300, *_guard_inputs(front=CFG.veto_mm - 1), mem) == TURN_LEFT
    assert guard.action(100_000, 0, 0, FORWARD, -300, *_guard_inputs(front=0), mem) == TURN_RIGHT
    assert guard.action(150_000, 0, 0, TURN_LEFT, -300, *_guard_inputs(front=0), mem) == TURN_LEFT
    assert guard.vetoes == 2


def test_guard_backs_off_when_stuck_beside_a_remembered_point_with_the_rear_clear():
    from firmware_py.kinds.sector.guard import REVERSE, TURN_LEFT, MotionGuard

    mem = ObstacleMemory(CFG)
    mem.points[(4, 0)] = (200, 0, 0)  # 200 mm from the robot's centre: within radius + backoff_near_mm
    period = robot_spec.CONTROL_PERIOD_US

    def run(rear: int, memory: ObstacleMemory) -> list[int]:
        guard = MotionGuard(CFG)
        return [guard.action(t * period, 0.0, 0.0, TURN_LEFT, 100, *_guard_inputs(rear=rear), memory)
                for t in range(CFG.stuck_us // period + 20)]

    acts = run(2000, mem)
    first = acts.index(REVERSE)
    assert first == CFG.stuck_us // period  # turning in place for stuck_us: not moved stuck_mm
    assert acts[first:first + CFG.backoff_us // period] == [REVERSE] * (CFG.backoff_us // period)
    assert acts[first + CFG.backoff_us // period] == TURN_LEFT
    assert REVERSE not in run(CFG.rear_clear_mm, mem)  # something behind: no back-off
    assert REVERSE not in run(2000, ObstacleMemory(CFG))  # nothing remembered near: no back-off


def test_guard_finishes_a_turn_toward_a_target_behind():
    """The table's bearing sectors meet behind the robot: one turn step there flips the target to
    the other side, and the table turned left, right, left on the spot for good. The guard keeps the
    turn's direction while the target is more than TURN_COMMIT_MRAD round; nearer ahead it lets the
    table turn back (an overshoot corrected)."""
    from firmware_py.kinds.sector.guard import TURN_COMMIT_MRAD, TURN_LEFT, TURN_RIGHT, MotionGuard

    guard, mem = MotionGuard(CFG), ObstacleMemory(CFG)
    wall = _guard_inputs(front=100, rear=100)  # squeezed: nothing to gain by the back-off
    behind = TURN_COMMIT_MRAD + 400
    acts = [guard.action(k * 50_000, 0, 0, a, b, *wall, mem)
            for k, (a, b) in enumerate([(TURN_LEFT, behind), (TURN_RIGHT, -behind), (TURN_LEFT, behind),
                                        (TURN_RIGHT, -behind)])]
    assert acts == [TURN_LEFT] * 4
    guard = MotionGuard(CFG)
    ahead = TURN_COMMIT_MRAD - 600
    assert [guard.action(k * 50_000, 0, 0, a, b, *wall, mem)
            for k, (a, b) in enumerate([(TURN_LEFT, ahead), (TURN_RIGHT, -ahead)])] == [TURN_LEFT, TURN_RIGHT]


def test_guard_steps_forward_out_of_turning_to_and_fro_when_the_front_is_open():
    """Left, right, left ... between two headings with the target just off ahead: after
    DITHER_REVERSALS reversals a forward step, if the front sensors read at least 2 x veto_mm;
    with something nearer ahead the table's turns stand."""
    from firmware_py.kinds.sector.guard import (
        DITHER_REVERSALS,
        FORWARD,
        TURN_LEFT,
        TURN_RIGHT,
        MotionGuard,
    )

    mem = ObstacleMemory(CFG)

    def run(front: int) -> list[int]:
        guard = MotionGuard(CFG)
        return [guard.action(k * 50_000, 0, 0, (TURN_LEFT, TURN_RIGHT)[k % 2], 200, *_guard_inputs(front=front), mem)
                for k in range(DITHER_REVERSALS + 2)]

    acts = run(2 * CFG.veto_mm)
    assert acts[DITHER_REVERSALS] == FORWARD and FORWARD not in acts[:DITHER_REVERSALS]
    assert FORWARD not in run(2 * CFG.veto_mm - 1)


def test_guard_backs_off_unless_something_closes_in_on_a_side():
    """Something between the side and rear-diagonal cones comes into the side sensor's view only as
    the robot backs onto it: a side reading that falls to veto_mm or under during a back-off ends it.
    A wall alongside, read as near from the start and no nearer, does not."""
    from firmware_py.kinds.sector.guard import REVERSE, TURN_LEFT, MotionGuard

    mem = ObstacleMemory(CFG)
    mem.points[(4, 0)] = (200, 0, 0)  # within radius + backoff_near_mm: a stuck robot backs off
    period = robot_spec.CONTROL_PERIOD_US
    start = CFG.stuck_us // period

    def run(side_mm: list[int]) -> list[int]:
        guard = MotionGuard(CFG)
        acts = []
        for t in range(start + len(side_mm)):
            ranges, status = _guard_inputs()
            ranges[2] = side_mm[max(0, t - start)]
            acts.append(guard.action(t * period, 0.0, 0.0, TURN_LEFT, 100, ranges,
                                     [V if r < 2000 else FAR for r in ranges], mem))
        return acts[start:]

    closing = [80, 70, 60, 50, 40, 30]
    assert run(closing) == [REVERSE] * 4 + [TURN_LEFT] * 2  # ends when the side reads 40 (veto_mm)
    alongside = [34] * 6
    assert run(alongside) == [REVERSE] * 6


def test_guard_turns_a_forward_step_the_collision_monitor_holds():
    """The table asked for forward against a remembered point in the path for 20 s while the
    collision monitor held the straight part, and the robot stood: once it has held HELD_TURN_US the
    guard turns toward the target instead."""
    from firmware_py.kinds.sector.guard import FORWARD, HELD_TURN_US, TURN_RIGHT, MotionGuard

    guard, mem = MotionGuard(CFG), ObstacleMemory(CFG)
    assert guard.action(0, 0, 0, FORWARD, -300, *_guard_inputs(), mem, held_us=HELD_TURN_US - 1) == FORWARD
    assert guard.action(50_000, 0, 0, FORWARD, -300, *_guard_inputs(), mem, held_us=HELD_TURN_US) == TURN_RIGHT


def test_a_recovery_back_off_also_ends_when_a_side_closes_in():
    """The planner's BACKUP (PlannedTarget.reverse) goes through the same check as the guard's own
    back-off: a side reading falling to veto_mm or under ends it."""
    from types import SimpleNamespace

    from firmware_py.kinds.sector.guard import REVERSE, TURN_LEFT, MotionGuard

    guard, mem = MotionGuard(CFG), ObstacleMemory(CFG)
    planner = SimpleNamespace(reverse=True, detouring=False)  # the two fields step() reads
    acts = []
    for k, side in enumerate([80, 70, 60, 50, 40, 30]):
        ranges, _ = _guard_inputs()
        ranges[6] = side
        acts.append(guard.step(k * 50_000, 0.0, 0.0, TURN_LEFT, 100, ranges,
                               [V if r < 2000 else FAR for r in ranges], mem, planner, 0)[0])  # type: ignore[arg-type]
    assert acts[:4] == [REVERSE] * 4 and REVERSE not in acts[4:]


def test_guard_turns_away_from_a_body_at_the_flank_then_steps_ahead():
    """A mover that walked up to the robot's right flank and stands there, in the blind gap ahead of
    the -90 degree sensor (which reads it 30 mm off; the -45 degree one does not see it, so the
    front veto does not act): a step ahead rubs into it, and the table, its target to the right,
    turned right and back on the spot. The guard turns left, away from it, whatever the
    table asks, until the flank ahead of the axle is clear, then takes ESCAPE_STEPS steps ahead; a
    body it cannot turn away from is given up after ESCAPE_US. A reading the map explains (nothing
    remembered that near: a block's corner) is left to the collision monitor, which has the corners."""
    from firmware_py.kinds.sector.guard import (
        ESCAPE_STEPS,
        ESCAPE_US,
        FORWARD,
        TURN_LEFT,
        TURN_RIGHT,
        MotionGuard,
    )

    mem = ObstacleMemory(CFG)
    mem.points[(0, -4)] = (0, -180, 0)  # the body's reading end point, as observe stores it

    def flank(*near: int) -> tuple[list[int], list[int]]:
        ranges = [2000] * N
        for i in near:
            ranges[i] = 30
        return ranges, [V if r < 2000 else FAR for r in ranges]

    guard = MotionGuard(CFG)
    ahead, behind = flank(6), flank(5, 6)  # the body ahead of the axle; after turning, behind it
    acts = [guard.action(0, 0, 0, FORWARD, -300, *ahead, mem),
            guard.action(50_000, 0, 0, TURN_RIGHT, -300, *ahead, mem)]
    acts += [guard.action(100_000 + k * 50_000, 0, 0, TURN_RIGHT, -300, *behind, mem)
             for k in range(ESCAPE_STEPS + 1)]
    assert acts == [TURN_LEFT, TURN_LEFT] + [FORWARD] * ESCAPE_STEPS + [TURN_RIGHT]
    left = MotionGuard(CFG)  # the body on the left: it turns right
    assert left.action(0, 0, 0, FORWARD, 300, *flank(2), mem) == TURN_RIGHT
    stuck = MotionGuard(CFG)
    period = robot_spec.CONTROL_PERIOD_US
    walled = flank(4, 6)  # something behind too: no back-off after stuck_us either
    acts = [stuck.action(k * period, 0, 0, TURN_RIGHT if k else FORWARD, -300, *walled, mem)
            for k in range(ESCAPE_US // period + 2)]
    assert acts[:ESCAPE_US // period] == [TURN_LEFT] * (ESCAPE_US // period)
    assert acts[-1] == TURN_RIGHT
    assert guard.action(0, 0, 0, FORWARD, -300, *flank(5, 6), mem) == FORWARD  # behind the axle: nothing to do
    assert MotionGuard(CFG).action(0, 0, 0, FORWARD, -300, *ahead, ObstacleMemory(CFG)) == FORWARD  # mapped
    # on the front-right diagonal with the target to the right: the front veto alone turned right,
    # into it, and the table back; the guard turns away from it, left, and keeps turning
    diagonal = MotionGuard(CFG)
    assert [diagonal.action(k * 50_000, 0, 0, a, -300, *flank(7), mem)
            for k, a in enumerate([FORWARD, TURN_RIGHT, FORWARD])] == [TURN_LEFT] * 3
    assert MotionGuard(CFG).action(0, 0, 0, FORWARD, -300, *flank(7), ObstacleMemory(CFG)) == TURN_RIGHT


def test_the_guards_flank_shortcut_never_changes_its_answer():
    """MotionGuard._escape skips the travel-gap geometry when no reading off the nose is under
    CONTACT_MM: over random readings, no such case has a step ahead blocked within veto_mm."""
    import random

    from firmware_py.control import collision

    rng = random.Random(3)
    for _ in range(20_000):
        status = [FAR] + [rng.choice((V, FAR, robot_spec.RANGE_TOO_CLOSE)) for _ in range(N - 1)]
        ranges = [rng.randint(robot_spec.RANGE_MIN_MM, 400) for _ in range(N)]
        if not collision.touching(ranges, status):
            assert collision.travel_gap_mm(ranges, status, False) >= CFG.veto_mm
