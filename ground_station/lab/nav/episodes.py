"""The episode loop of `qnav bench nav`: (scenario episodes, controller) -> rows.

`run_twin(episodes, maps, controller)` rolls a controller out on the
kinematic twin with the episodes' obstacles (one jitted call for all of
them); `run_hil(episodes, maps, controller)` drives each episode on the
in-process lockstep rig (`ground_station.lab.rigs.lockstep.LockstepRig`: pymunk
plant + the robot's own `RobotNode`/`Controller`, the controller's table
exported as a `.qtab`) with the episode's discs and movers as pymunk bodies
(`sim_bridge.obstacles.ObstacleLayer`). Both return one plain dict per
episode and depend only on their arguments, so episode lists can be split
and farmed out; `summarise(rows)` gives the figures of a table row.

Outcome per episode: success (goal reached, no contact), collision (twin:
the disc touched a wall, disc or mover; HIL: any bumper contact event),
loop/timeout, no_route (the robot reported that no route to the goal exists:
the right answer on a blocked-passage episode without a detour,
`scenario.blocked_episodes`). Rows of blocked episodes carry
`blocked` = {"detour": label}. Path ratio = driven length / the planned waypoint path length
(successful episodes); time to goal in seconds of robot time; a near miss is
a control period whose clearance to an unmapped obstacle (rim to the
nearest disc or mover) is below `NEAR_MISS_MM` without contact.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from firmware_py import robot_spec
from ground_station.lab.nav.controllers import BenchController, NavController
from ground_station.lab.nav.obstacle_twin import (
    COLLISION,
    LOOP,
    NEAR_MISS_MM,
    NO_ROUTE,
    SUCCESS,
    TIMEOUT,
    nav_eval_kernel,
    obstacle_clearance_mm,
)
from ground_station.lab.nav.planned import budget_periods, run_twin_planned
from ground_station.lab.nav.scenario import Episode, episode_arrays
from ground_station.learn.sector.twin import TwinRobot, encoder_arrays
from ground_station.maps import GridMap

OUTCOMES = {SUCCESS: "success", COLLISION: "collision", LOOP: "loop", TIMEOUT: "timeout", NO_ROUTE: "no_route"}
PERIOD_S = robot_spec.CONTROL_PERIOD_US / 1e6
BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS = 400.0, 4.0, 400


def plan_length(ep: Episode) -> float:
    pts = [ep.start[:2], *ep.waypoints]
    return float(sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(pts[:-1], pts[1:], strict=True)))


def run_twin(eps: list[Episode], maps: dict[str, GridMap], ctrl: NavController,
             robot: TwinRobot | None = None) -> list[dict]:
    """Greedy rollouts of `ctrl` on the twin over `eps` (obstacles included), the twin playing `robot`
    (`twin.TwinRobot` of a profile; default the built-in robot)."""
    robot = robot or TwinRobot()
    if not eps:
        return []
    a = episode_arrays(eps, maps)
    enc = ctrl.encoder
    n = len(eps)
    outcome = np.zeros(n, dtype=np.int64)
    path = np.zeros(n)
    steps = np.zeros(n, dtype=np.int64)
    minclear = np.zeros(n)
    near = np.zeros(n, dtype=np.int64)
    q = np.ascontiguousarray(ctrl.q, dtype=np.float64)
    if ctrl.local is not None:  # the robot's own local planner code in a Python loop (nav/planned.py)
        outcome, path, steps, minclear, near = run_twin_planned(eps, maps, ctrl, BUDGET_BASE, BUDGET_FACTOR,
                                                                STALL_STEPS, robot)
        return _rows(eps, outcome, path, steps, minclear, near)
    sectors, sensors, edges, which = encoder_arrays(enc)
    nav_eval_kernel(q, a["occ"], a["dims"], a["cells"], a["map"],
                    a["start"], a["goal"], a["wp"], a["nwp"], a["rem"], a["discs"], a["nd"], a["movers"],
                    a["nm"], sectors, sensors, edges, which, int(ctrl.guidance == "path"),
                    BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS, outcome, path, steps, minclear, near, robot.arrays())
    return _rows(eps, outcome, path, steps, minclear, near)


def _rows(eps: list[Episode], outcome: np.ndarray, path: np.ndarray, steps: np.ndarray, minclear: np.ndarray,
          near: np.ndarray) -> list[dict]:
    rows = []
    for i, ep in enumerate(eps):
        o = int(outcome[i])
        rows.append({"outcome": OUTCOMES[o], "success": o == SUCCESS, "collision": o == COLLISION,
                     "path_ratio": float(path[i] / plan_length(ep)) if o == SUCCESS else None,
                     "time_s": float(steps[i] * PERIOD_S), "near_miss_periods": int(near[i]),
                     "min_clearance_mm": round(float(minclear[i]), 1), "discs": len(ep.discs),
                     "movers": len(ep.movers), **_blocked_row(ep)})
    return rows


def answered_right(row: dict) -> bool:
    """An episode row's answer was right: the goal reached, or "no route" on a blocked-passage
    episode without a detour (`scenario.blocked_episodes`: there it is the right answer)."""
    return bool(row["success"] or (row["outcome"] == "no_route" and row.get("blocked", {}).get("detour") is False))


def _blocked_row(ep: Episode) -> dict:
    return {"blocked": {"detour": bool(ep.blocked["detour"])}} if ep.blocked else {}


def run_hil(eps: list[Episode], maps: dict[str, GridMap], ctrl: BenchController,
            progress: Callable[[], None] | None = None, max_sim_s: float | None = None,
            index_offset: int = 0, step_cpu: bool = False, vehicle: Any = None,
            profile: Any = None, robot: Any = None) -> list[dict]:
    """Each episode on the lockstep rig with its obstacles in the pymunk world.

    Episode i of the list runs with plant seed `ep.seed + index_offset + i`:
    a slice of a longer list passes its offset and gets the same rows.
    `step_cpu`: add each tick's Controller.step CPU time (`qnav bench
    controller`; a timing, so never in `qnav bench nav`'s reproducible rows).
    `vehicle`: the robot's VehicleConfig (default: its parameters' defaults);
    `profile`: the plant's sim_bridge.profiles.PlantProfile (default: the sim's default config);
    `robot`: the robot profile (firmware_py.profile.RobotProfile) the sim and the robot play (default the
    built-in robot)."""
    from ground_station.lab.rigs.lockstep import LockstepRig
    from sim_bridge.obstacles import ObstacleLayer

    rows = []
    policies: dict[str, object] = {}
    for i, ep in enumerate(eps):
        gm = maps[ep.map]
        if ep.map not in policies:
            policies[ep.map] = ctrl.policy(ep.map)
        goals = [(round(x), round(y)) for x, y in (ep.waypoints if ctrl.guidance == "path" else [ep.goal_mm])]
        limit = max_sim_s or budget_periods(plan_length(ep), BUDGET_BASE, BUDGET_FACTOR) * PERIOD_S
        t0 = time.perf_counter()
        start = (ep.start[0] / 1000.0, ep.start[1] / 1000.0, ep.start[2])
        near = 0
        minclear = math.inf
        driven = 0.0
        with LockstepRig(gm.occ, policies[ep.map], start, goals, seed=ep.seed + index_offset + i,  # type: ignore[arg-type]
                         vehicle=vehicle, profile=profile, robot=robot) as rig:
            layer = ObstacleLayer(rig.plant.world, ep.discs, ep.movers)
            rig.plant.obstacles = layer  # movers move at the end of every period, as in the twin
            end_us = round(limit * 1e6)
            cap_us = 3 * end_us
            last = rig.plant.world.pose
            route_plans = 0
            while rig.plant.time_us < end_us and not rig.runner.done.is_set():
                rig.tick()
                if max_sim_s is None:  # the budget is the current plan's, as in the twin (nav.planned)
                    end_us, route_plans = _rebase_budget(rig, end_us, route_plans, cap_us)
                pose = rig.plant.world.pose
                driven += math.hypot(pose.x - last.x, pose.y - last.y) * 1000.0
                last = pose
                cl = float(obstacle_clearance_mm(pose.x * 1000.0, pose.y * 1000.0, layer.discs, layer.movers,
                                                 float(rig.plant.world.geometry.robot_radius_mm)))
                minclear = min(minclear, cl)
                if 0.0 < cl < NEAR_MISS_MM:
                    near += 1
            result = rig.runner.result if rig.runner.done.is_set() else "timeout"
            contacts = rig.plant.world.contact_events
            sim_s = rig.plant.time_us / 1e6
            cpu = [round(v / 1000, 1) for v in rig.ctrl.step_cpu_ns]
            work = rig.ctrl.background  # the planner's search, stepped between ticks (off the tick)
            off_tick = {"background_cpu_us": round(work.cpu_ns / 1000, 1), "background_runs": work.runs,
                        "background_max_us": round(work.max_cpu_ns / 1000, 1)}
        reached = result == "reached"
        success = reached and contacts == 0
        outcome = "success" if success else ("collision" if contacts else (
            "timeout" if result == "timeout" else
            "no_route" if result.startswith("stopped: no route") else "stopped"))  # the robot said so (Controller._no_route)
        rows.append({"outcome": outcome, "success": success, "collision": contacts > 0, "result": result,
                     "contacts": contacts, "path_ratio": driven / plan_length(ep) if success else None,
                     "time_s": sim_s, "near_miss_periods": near, "min_clearance_mm": round(minclear, 1),
                     "discs": len(ep.discs), "movers": len(ep.movers), **_blocked_row(ep),
                     "wall_s": round(time.perf_counter() - t0, 3), **({"step_cpu_us": cpu, **off_tick} if step_cpu else {})})
        if progress is not None:
            progress()
    return rows


def _rebase_budget(rig: Any, end_us: int, routes: int, cap_us: int) -> tuple[int, int]:
    """When the robot's sector planner takes a new whole-map route (a detour through another door;
    the first route of a round of recoveries), the episode's sim-time budget becomes at least that
    route's own (BUDGET_BASE + BUDGET_FACTOR x its length in forward periods, from now), at most
    `cap_us`. Returns (end_us, the planner's routes_taken seen)."""
    local = getattr(rig.ctrl.driver, "local", None)
    if local is None or local[0].routes_taken == routes:
        return end_us, routes
    planner = local[0]
    periods = budget_periods(planner.route_mm, BUDGET_BASE, BUDGET_FACTOR)
    return min(cap_us, max(end_us, rig.plant.time_us + round(periods * PERIOD_S * 1e6))), planner.routes_taken


def run_job(job: dict) -> list[dict]:
    """One campaign job of `qnav bench nav` (a fresh worker may run it): the
    controller `job["controller"]` built from the policy file, the maps loaded
    from their specs, then `run_twin` or `run_hil` over `job["episodes"]`."""
    from firmware_py.policy import load_policy
    from ground_station.lab.nav.controllers import kind_controllers
    from ground_station.maps import load_map

    ctrl = kind_controllers(load_policy(job["policy"]), (job["controller"],))[0]
    maps = {name: load_map(spec) for name, spec in job["maps"].items()}
    if job["kind"] == "twin":
        assert isinstance(ctrl, NavController), f"{ctrl.name} has no continuous twin"
        return run_twin(job["episodes"], maps, ctrl, twin_robot(job.get("robot")))
    from firmware_py.profile import load_profile
    from sim_bridge.profiles import profile

    plant = profile(job["profile"]) if job.get("profile") else None
    robot = load_profile(job["robot"]) if job.get("robot") else None
    return run_hil(job["episodes"], maps, ctrl, index_offset=job["offset"], profile=plant, robot=robot)


def twin_robot(robot_file: str | None) -> TwinRobot:
    """The twin of a robot profile file (None: the built-in robot)."""
    if robot_file is None:
        return TwinRobot()
    from firmware_py.profile import load_profile

    return TwinRobot.of_profile(load_profile(robot_file))


def wilson95(k: int, n: int) -> list[float]:
    """95 % Wilson score interval of a rate k / n (sound at 0 and n, unlike k/n +- 1.96 sigma)."""
    if n == 0:
        return [0.0, 1.0]
    z, p = 1.959964, k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return [round(max(0.0, centre - half), 4), round(min(1.0, centre + half), 4)]


def mcnemar_exact(rows_a: list[dict], rows_b: list[dict]) -> dict:
    """Paired comparison of two controllers' successes on the same episodes (in the same order):
    episodes only A succeeded in, only B, and the exact two-sided McNemar p (binomial on them)."""
    a_only = sum(1 for x, y in zip(rows_a, rows_b, strict=True) if x["success"] and not y["success"])
    b_only = sum(1 for x, y in zip(rows_a, rows_b, strict=True) if y["success"] and not x["success"])
    n, k = a_only + b_only, min(a_only, b_only)
    p = 1.0 if n == 0 else min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n)
    return {"a_only": a_only, "b_only": b_only, "p_exact": p}


def paired_time(rows_a: list[dict], rows_b: list[dict]) -> dict:
    """Time to goal on the episodes both controllers succeeded in (same episodes, same order): how
    many A finished sooner, B sooner, the median of A's time minus B's (s), and the exact two-sided
    sign test p on the untied ones."""
    d = [x["time_s"] - y["time_s"] for x, y in zip(rows_a, rows_b, strict=True) if x["success"] and y["success"]]
    a_f, b_f = sum(v < 0 for v in d), sum(v > 0 for v in d)
    n, k = a_f + b_f, min(a_f, b_f)
    p = 1.0 if n == 0 else min(1.0, 2 * sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n)
    return {"both": len(d), "a_faster": a_f, "b_faster": b_f,
            "median_diff_s": round(float(np.median(d)), 2) if d else None, "p_sign": p}


def summarise(rows: list[dict]) -> dict:
    """success_rate, collision_rate (each with its 95 % Wilson interval), path_ratio_mean,
    time_to_goal_mean_s, near_miss_rate (episodes with a near miss), no_route_rate (episodes the
    robot ended with "no route"), episodes; when rows are of blocked-passage episodes, `blocked`:
    per label, "detour" (episodes, success_rate and its interval, no_route_rate: wrongly given
    up) and "none" (episodes, no_route_reported: the share rightly given up, its interval,
    collision_rate)."""
    n = len(rows)
    ok = [r for r in rows if r["success"]]
    ratios = [r["path_ratio"] for r in ok if r["path_ratio"] is not None]
    collisions = sum(r["collision"] for r in rows)
    out = {
        "episodes": n,
        "success_rate": len(ok) / n if n else 0.0,
        "success_ci95": wilson95(len(ok), n),
        "collision_rate": collisions / n if n else 0.0,
        "collision_ci95": wilson95(collisions, n),
        "path_ratio_mean": float(np.mean(ratios)) if ratios else None,
        "time_to_goal_mean_s": float(np.mean([r["time_s"] for r in ok])) if ok else None,
        "near_miss_rate": sum(r["near_miss_periods"] > 0 for r in rows) / n if n else 0.0,
        "no_route_rate": sum(r["outcome"] == "no_route" for r in rows) / n if n else 0.0,
        "outcomes": {k: sum(r["outcome"] == k for r in rows) for k in sorted({r["outcome"] for r in rows})},
    }
    if any(r.get("blocked") for r in rows):
        yes = [r for r in rows if r.get("blocked") and r["blocked"]["detour"]]
        no = [r for r in rows if r.get("blocked") and not r["blocked"]["detour"]]
        won = sum(r["success"] for r in yes)
        gave_up = sum(r["outcome"] == "no_route" for r in no)
        out["blocked"] = {
            "detour": {"episodes": len(yes), "success_rate": won / len(yes) if yes else 0.0,
                       "success_ci95": wilson95(won, len(yes)),
                       "no_route_rate": sum(r["outcome"] == "no_route" for r in yes) / len(yes) if yes else 0.0},
            "none": {"episodes": len(no), "no_route_reported": gave_up / len(no) if no else 0.0,
                     "no_route_reported_ci95": wilson95(gave_up, len(no)),
                     "collision_rate": sum(r["collision"] for r in no) / len(no) if no else 0.0},
        }
    return out
