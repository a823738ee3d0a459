"""Twin rollouts of a sector policy steering on the robot's local planner.

`run_twin_planned(episodes, maps, controller)` is `episodes.run_twin` for a
controller with a `LocalPlannerConfig` (`NavController.local`): per control
period the twin's physics, movers and sensing are the bench kernel's
(`lab.nav.obstacle_twin.obs_period_step`, all eight sensors read), and the
steering is the robot's own Python: `firmware_py.kinds.sector.memory.ObstacleMemory`
fed with the readings at the twin's pose, `PlannedTarget.target` for the
current waypoint (reset per waypoint, as the controller does per mission
item; its search stepped after each period, as the lockstep robot's node
steps it after each tick, so an answer is one period old; the speed it
asks for is not applied: the twin's kernel moves by whole actions, and
with answers one period old it asks for full speed anyway), the table's greedy action on the sector state toward that target,
and `MotionGuard.action` on it (one guard per episode: one drive), then the
robot's collision monitor (`firmware_py.control.collision.limit` with the
robot's default CM_* parameters, on the readings, the remembered points and
the map's corners near the pose, as `Controller._outputs` applies it): a
straight step it stops is a period standing still; its slow zone is not
modelled (the kernel moves by whole actions at one speed).
The planner's recoveries act as on the robot: a period it asks to stand
still (waiting for a mover, waiting for a whole-map answer) the robot does
not move while the movers walk and the sensors read, its back-off is a
reverse step, its give-way is driven as a detour is, and its "no route" ends
the episode as NO_ROUTE (the robot reports it and holds). Budget, loop rule,
near misses and outcomes are `nav_eval_kernel`'s, so its rows sit beside the
other controllers' in `qnav bench nav`, except that progress, and the period
budget, are measured along the robot's current plan while it follows a
whole-map route (a detour through another door first leads away from the
waypoint; the first route of each round of recoveries, and another way round
once the route followed closed, start a new count and a budget for its own
length, up to three times the episode's), and periods the planner's
recoveries hold the robot still, back it off or drive it aside (WAIT,
GIVE_WAY, BACKUP, CLEAR, a whole-map route held or not yet answered) do not
count toward the loop rule: they are bounded by the robot's own rules (at
most 3 x max_rounds rounds), not aimless, and the budget still bounds them.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from firmware_py import robot_spec
from firmware_py.background import Background
from firmware_py.control import collision
from firmware_py.control.collision import mapped_readings
from firmware_py.kinds.sector.guard import MotionGuard
from firmware_py.kinds.sector.memory import ObstacleMemory
from firmware_py.kinds.sector.recoveries import BACKUP, CLEAR, GIVE_WAY, GLOBAL, WAIT, PlannedTarget
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.layout import Layout
from firmware_py.mapdata import grid_from_rows
from firmware_py.vehicle import VehicleConfig
from ground_station.lab.nav.controllers import NavController
from ground_station.lab.nav.obstacle_twin import (
    COLLISION,
    LOOP,
    NO_ROUTE,
    PERIOD_S,
    TIMEOUT,
    obs_period_step,
    obstacle_clearance_mm,
    period_end,
    sense_obs,
    step_movers,
)
from ground_station.lab.nav.scenario import Episode, rollout_arrays
from ground_station.learn.sector.kernels import FWD_MM_PER_PERIOD
from ground_station.learn.sector.twin import (
    G_FWD,
    TW_GEO,
    TwinRobot,
    bearing_mrad,
    encode_fast,
    encoder_arrays,
)
from ground_station.maps import GridMap

PERIOD_US = robot_spec.CONTROL_PERIOD_US


def budget_periods(length_mm: float, budget_base: float, budget_factor: float,
                   fwd_mm_per_period: float = FWD_MM_PER_PERIOD) -> float:
    """An episode's (or a plan's) period budget: `budget_base` + `budget_factor` x the periods a
    `length_mm` drive takes at full forward speed (the twin's rule; run_hil takes it in sim time)."""
    return budget_base + budget_factor * length_mm / fwd_mm_per_period


def grid_of(gm: GridMap):
    """The map as the robot's `OccupancyGrid` (what a `.qtab` with the map carries)."""
    rows = ["".join("@" if v else "." for v in row) for row in gm.occ.tolist()]
    return grid_from_rows(rows, round(gm.cell_size_m * 1000))


def rollout(ep: Episode, gm: GridMap, ctrl: NavController, budget_base: float, budget_factor: float,
            stall_steps: int, robot: TwinRobot | None = None,
            make_planner: Callable[..., PlannedTarget] | None = None,
            watch: Callable[[float, float, np.ndarray], None] | None = None) -> tuple[int, float, int, float, int, int]:
    """One greedy episode of the twin playing `robot` (default the built-in one); returns (outcome,
    driven mm, periods, min clearance, near-miss periods, plans). `make_planner(grid, cfg, work,
    radius_mm)`: the tick's side of the planner (default `PlannedTarget`, or the controller's own:
    `NavController.planner`; a tracing subclass in `nav.decisions`). `watch(x, y, movers)`: called
    after every period with the robot's position (mm) and the movers (x, y, vx, vy, r, yields rows)."""
    assert ctrl.local is not None
    robot = robot or TwinRobot()
    tw = robot.arrays()
    radius = float(robot.radius_mm)
    fwd = float(tw[TW_GEO][G_FWD])
    layout = robot.layout()
    occ = np.ascontiguousarray(gm.occ, dtype=np.uint8)
    h, w = occ.shape
    c = gm.cell_size_m * 1000.0
    sectors, sensors, edges, _ = encoder_arrays(ctrl.encoder)
    which = np.ones(robot_spec.SENSOR_COUNT, dtype=np.bool_)
    discs, movers, wps, rem, plan_len = rollout_arrays(ep, ctrl.guidance == "path")
    x, y, th = ep.start
    budget = int(budget_periods(plan_len, budget_base, budget_factor, fwd))
    phi = math.hypot(x - wps[0, 0], y - wps[0, 1]) + rem[0]
    grid = grid_of(gm)
    cfg = ctrl.local.for_body(robot.radius_mm)  # the clearances round the robot's body, as the kind does
    memory = ObstacleMemory(cfg, layout)
    work = Background(threaded=False)  # stepped after each period, as the lockstep robot's node does
    planner = (make_planner or ctrl.planner)(grid, cfg, work, robot.radius_mm)
    guard = MotionGuard(cfg, layout)
    corners = collision.MapCorners(grid)
    held = 0  # periods in a row the collision monitor has stopped the straight part
    ranges = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
    status = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
    rw = np.zeros(6)  # the reward is not needed here
    q = ctrl.q
    k, best, since, path, t, near = 0, phi, 0, 0.0, 0, 0
    outcome = TIMEOUT
    minclear = float(obstacle_clearance_mm(x, y, discs, movers, radius))
    sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, movers, tw)
    route_plans = 0  # PlannedTarget.routes_taken when the current plan's count began
    budget0 = budget
    while t < budget:
        xm, ym, thm = round(x), round(y), round(th * 1000.0)
        rl, sl = ranges.tolist(), status.tolist()
        memory.observe(grid, xm, ym, thm, rl, sl, t * PERIOD_US)
        tx, ty, speed = planner.target(t * PERIOD_US, x, y, (round(wps[k, 0]), round(wps[k, 1])), memory)
        # the planner's recoveries hold the robot still (or back it off, or drive it aside) on purpose, for a
        # bounded time: not aimless, so those periods do not count toward the loop rule (the budget still
        # bounds them)
        recovering = planner.mode in (WAIT, GIVE_WAY, BACKUP, CLEAR) or (planner.mode == GLOBAL and speed == 0)
        if planner.no_route:
            outcome = NO_ROUTE  # the robot's recoveries ran out and it reports it (the controller holds)
            break
        b = bearing_mrad(x, y, th, tx, ty)
        s = encode_fast(b, ranges, status, sectors, sensors, edges)
        a, speed = guard.step(t * PERIOD_US, x, y, int(np.argmax(q[s])), b, rl, sl, memory, planner, speed,
                              held * PERIOD_US)
        if speed and monitor_stops(a, xm, ym, thm, rl, sl, memory, corners, layout):
            speed = 0  # the collision monitor removed the straight part: a step into nothing but a stand
            held += 1  # as the controller's DriveTick.blocked_us, up to the last tick
        else:
            held = 0
        k0 = k
        if speed == 0:  # a recovery stands still: the movers walk on, the sensors read
            step_movers(movers, occ, c, discs, x, y, radius, PERIOD_S)
            sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, movers, tw)
            hit, success, driven = False, False, 0.0
        else:
            x, y, th, phi, _, _, hit, success, driven, k = obs_period_step(
                occ, h, w, c, x, y, th, phi, wps, rem, len(wps), k, a, rw, which, ranges, status,
                sectors, sensors, edges, discs, movers, tw)
        path += driven
        t += 1
        if watch is not None:
            watch(x, y, movers)
        if hit:
            outcome, minclear = COLLISION, 0.0
            break
        if k != k0:
            planner.reset()
        if planner.mode == GLOBAL and not success:
            # progress along the robot's current plan: its global route (a detour through another
            # door first leads away from the waypoint) plus the waypoints after it; a new route (the
            # search count when this tick's answer was made) is a new plan, measured from where it starts
            phi = planner.route_mm + float(rem[k])
            if planner.routes_taken != route_plans:
                route_plans, best, since = planner.routes_taken, phi, 0
                # the budget too is the current plan's (a long detour through another door is no
                # timeout), at most three times the episode's own
                budget = min(max(budget, t + int(budget_periods(phi, budget_base, budget_factor, fwd))),
                             3 * budget0)
        work.run_pending()  # after the count above: the search it runs answers the next tick
        counted = since
        end, best, since, minclear, near = period_end(x, y, discs, movers, success, phi, best, since, stall_steps,
                                                      minclear, near, radius)
        if recovering and since > counted:
            since = counted
            if end == LOOP:
                end = -1
        if end >= 0:
            outcome = end
            break
    return outcome, path, t, minclear, near, planner.plans


_VEHICLE = VehicleConfig()


def monitor_stops(action: int, x_mm: int, y_mm: int, th_mrad: int, ranges: list[int], status: list[int],
                  memory: ObstacleMemory, corners: collision.MapCorners, layout: Layout = DEFAULT_LAYOUT) -> bool:
    """Whether the robot's collision monitor removes `action`'s straight part at this pose (its
    stop zone; `Controller._outputs` feeds it the same readings, remembered points and corners), the
    sector readings at `layout`'s angles (the twin's robot; default the built-in one)."""
    left, right = robot_spec.ACTION_WHEEL_SPEEDS_MM_S[action]
    if left + right == 0:
        return False  # turning in place: left alone
    lim = layout.max_wheel_speed_mm_s
    left, right = max(-lim, min(lim, left)), max(-lim, min(lim, right))
    fan = collision.DEFAULT_FAN if layout == DEFAULT_LAYOUT else collision.Fan(layout)
    cfg = _VEHICLE
    radius = layout.robot_radius_mm
    seen = [(px, py) for px, py, _ in memory.points.values()]
    seen += corners.near(x_mm, y_mm, cfg.collision_slow_mm + 2 * radius)
    if left == right:  # driving straight: only what lies within stop_mm + radius of the centre can stop it
        reach = cfg.collision_stop_mm + radius + 1
        mount = layout.mount_mm
        if not any(st == robot_spec.RANGE_TOO_CLOSE or (st == robot_spec.RANGE_VALID and mount + r <= reach)
                   for r, st in zip(ranges, status, strict=True)) and not any(
                (px - x_mm) ** 2 + (py - y_mm) ** 2 <= reach * reach for px, py in seen):
            return False  # the same answer as limit's, without its geometry (the twin's hot loop)
    near = collision.robot_frame(seen, (x_mm, y_mm, th_mrad)) if seen else []
    mapped = mapped_readings(corners.grid, (x_mm, y_mm, th_mrad), ranges, status, fan=fan)
    return collision.limit(left, right, ranges, status, cfg.collision_stop_mm, cfg.collision_slow_mm,
                           cfg.collision_slow_pct, near, mapped, fan)[2] == "stop"


def run_twin_planned(eps: list[Episode], maps: dict[str, GridMap], ctrl: NavController, budget_base: float,
                     budget_factor: float, stall_steps: int, robot: TwinRobot | None = None) -> tuple[np.ndarray, ...]:
    """All episodes; arrays (outcome, path, steps, minclear, near) as the bench kernels fill them."""
    n = len(eps)
    outcome = np.zeros(n, dtype=np.int64)
    path, minclear = np.zeros(n), np.zeros(n)
    steps, near = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    for i, ep in enumerate(eps):
        outcome[i], path[i], steps[i], minclear[i], near[i], _ = rollout(
            ep, maps[ep.map], ctrl, budget_base, budget_factor, stall_steps, robot)
    return outcome, path, steps, minclear, near

