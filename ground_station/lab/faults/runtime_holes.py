"""The robot-runtime findings of issue 29, one scenario each (findings 2 and 6 are
`mav_failsafe_garbage` and `can_forged_tick_pace` in hostile_holes).

All on the lockstep rig (`rigs.lockstep.LockstepRig`: the pymunk plant and the
real RobotNode + Controller on a python-can virtual bus), MAVLink through the
real `MavNode` polled after every tick (hostile_holes._PolledNode), frames
built by pymavlink:

- `mav_hold_ends_exploration` (finding 1): armed in Hold, MAV_CMD_USER_1
  (explore) starts the global-localisation wander; then, at a seeded moment,
  SET_MODE Hold, a GCS failsafe (the GCS falls silent, FS_GCS_TOUT_MS 500 ms)
  or a disarm: the first zero command comes at the tick after the one that
  handled it, every later command is zero, the wander has ended.
- `activation_worst_case` (findings 3 and 4): a legal worst-case policy (the
  largest map the loader accepts, the planner's extreme metadata) activated
  while the shipped sector policy drives is refused at once with the reason;
  after Hold (armed, where the 37 s link freeze was measured) it is built on
  a worker while the ticks go on: the old policy stays active until the new
  one is ready, every tick is answered, no step takes a control period of
  CPU, no FAULT.
- `planner_worst_case` (finding 4): the sector policy with the planner's
  extreme legal metadata on a scenario episode with 3 discs + 2 movers: the
  search runs off the tick (firmware_py.background), no step takes a control
  period of CPU, no FAULT, every tick answered. The result (reached or not)
  is not judged: extreme settings are legal, not good.
- `param_save_full_disk` (finding 5): PARAM_SET while the disk is full (the
  write fails with ENOSPC): the value is echoed and in effect, an ERROR
  STATUSTEXT says it is lost at reboot, a reboot-time load does not have it,
  no handler raised; after space is back the next save sticks.
- `goal_refusals` (finding 7): seeded goals outside the map, inside a wall or
  closer to a wall than the robot's radius, by SET_POSITION_TARGET_LOCAL_NED,
  DO_REPOSITION and a mission item: refused with a reason naming why, the
  robot never starts driving; a VALID range reading above the sensor's
  maximum is not used as an obstacle.
"""

from __future__ import annotations

import errno
import random
import tempfile
from array import array
from pathlib import Path
from typing import Any
from unittest import mock

from firmware_py import policy as fmt
from firmware_py import robot_spec
from firmware_py.mapdata import MAX_SIDE_MM
from firmware_py.shipped_policies import resolve_policy_spec
from firmware_py.vehicle import CtrlState, Mode
from ground_station.lab.faults.can_faults import _drive_to, _fault_time, _first_fault, _stopped_by
from ground_station.lab.faults.common import ScenarioResult, register, trials
from ground_station.lab.faults.hostile_holes import GCS, _PolledNode
from ground_station.lab.rigs.lockstep import PERIOD_US, LockstepRig, paper10

# the planner's extreme legal metadata (firmware_py.kinds.sector.config.LocalPlannerConfig.from_metadata's bounds)
# (the window: (3000 + 2 x 3500) / 50 = 200 raster cells a side, config.MAX_WINDOW_CELLS)
EXTREME_PLANNER = {"raster_mm": 50, "window_mm": 3500, "max_plan_mm": 3000, "max_points": 1000,
                   "lookahead_mm": 5000, "soft_mm": 250, "los_clear_mm": 250, "obstacle_clear_mm": 200,
                   "margin_mm": 1000, "see_mm": 2000, "memory_us": 100_000_000}


def _sector_variant(planner: dict | None = None, rows: list[str] | None = None, cell_mm: int | None = None) -> bytes:
    """The shipped sector table with other planner metadata and/or another map."""
    base = fmt.load_policy(resolve_policy_spec("policies:sector"))
    meta = dict(base.metadata)
    if planner is not None:
        meta["local_planner"] = planner
    geometry = None
    if rows is not None:
        meta["map_grid"] = rows
        geometry = fmt.MapGeometry(cell_mm or 500, len(rows[0]), len(rows))
    table = array(fmt.DTYPES[fmt.DTYPE_CODES[base.dtype]][1], base.table)
    return fmt.dump_policy(base.encoder, table, base.dtype, base.scale, goals=base.goals, cell_mm=base.cell_mm,
                           metadata=meta, control_period_us=base.control_period_us,
                           map_geometry=geometry or base.map_geometry)


def largest_legal_map_policy() -> bytes:
    """A walled square map as wide as the metadata allows, MAX_SIDE_MM a side, extreme planner."""
    width = 120
    while True:
        rows = ["@" * width] + ["@" + "." * (width - 2) + "@"] * (width - 2) + ["@" * width]
        try:
            return _sector_variant(EXTREME_PLANNER, rows, MAX_SIDE_MM // width)
        except ValueError:  # the metadata's size limit: a little narrower
            width -= 1


def _sector_rig(seed: int, policy_bytes: bytes | None = None, with_goal: bool = True) -> tuple[random.Random, LockstepRig]:
    """The sector policy (or a variant) on paper10 from a seeded free cell to a far one."""
    rng = random.Random(seed)
    gm = paper10()
    pol = fmt.load_policy(policy_bytes if policy_bytes is not None else resolve_policy_spec("policies:sector"))
    free = [(c, r) for r in range(gm.height) for c in range(gm.width) if not gm.occ[r, c]]
    a, b = rng.sample(free, 2)
    while abs(a[0] - b[0]) + abs(a[1] - b[1]) < 6:
        a, b = rng.sample(free, 2)
    sx, sy = robot_spec.cell_center_mm(*a, gm.height)
    gx, gy = robot_spec.cell_center_mm(*b, gm.height)
    start = (sx / 1000, sy / 1000, rng.uniform(-3.1, 3.1))
    return rng, LockstepRig(gm.occ, pol, start, [(gx, gy)] if with_goal else [], seed=seed)


def _policy_id(rig: LockstepRig) -> int | None:
    return rig.ctrl.policy.policy_id if rig.ctrl.policy is not None else None


def _max_step_problem(rig: LockstepRig, res: ScenarioResult) -> list[str]:
    worst = max(rig.ctrl.step_cpu_ns, default=0) // 1000
    res.figures["max_step_cpu_us"] = max(res.figures.get("max_step_cpu_us", 0), worst)
    return [f"a step took {worst} us of CPU (period {PERIOD_US} us)"] if worst >= PERIOD_US else []


# --- finding 1 -----------------------------------------------------------------------------------

@register("mav_hold_ends_exploration", small=3, large=30, unit="episodes",
          what="exploring (USER_1) then SET_MODE Hold / GCS failsafe / disarm -> zero command at the next tick")
def hold_ends_exploration(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    stops = ("set_mode hold", "gcs failsafe", "disarm")
    for i in trials(count, progress):
        rng, rig = _sector_rig(seed * 7919 + 11000 + i, with_goal=False)
        stop = stops[(seed + i) % len(stops)]
        problems: list[str] = []
        with rig:
            polled = _PolledNode(rig, 500)
            m, gcs = polled.m, polled.m.MAVLink(None, *GCS)

            def send(msg, gcs=gcs, polled=polled) -> None:
                polled.inbox.put(bytes(msg.pack(gcs)))

            def beat(gcs=gcs, m=m) -> bytes:
                return gcs.heartbeat_encode(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)

            send(beat())
            rig.run_until(3 * PERIOD_US)
            send(gcs.command_long_encode(1, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
            rig.tick()
            send(gcs.command_long_encode(1, 1, m.MAV_CMD_USER_1, 0, 1, 0, 0, 0, 0, 0, 0))
            rig.tick()
            # the poll that handles it runs after that tick's answer, in the robot's thread: the
            # next tick's answer comes after it (read at once, a loaded machine lost the race)
            rig.tick()
            if not rig.ctrl.exploration.running:
                problems.append(f"setup: not exploring (armed {rig.ctrl.armed}, state {rig.ctrl.state.name}, "
                                f"robot said {polled.texts[-3:]})")
            t_stop = rig.time_us + _fault_time(rng) // 2  # 0.5 .. 1.5 s of wandering
            while rig.time_us < t_stop:
                send(beat())
                rig.tick()
            moving = any(c[1] or c[2] for c in rig.commands if c[0] >= t_stop - 10 * PERIOD_US)
            if not moving:
                problems.append("setup: the wander did not move the wheels")
            if stop == "set_mode hold":
                send(gcs.set_mode_encode(1, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(Mode.HOLD)))
            elif stop == "disarm":
                send(gcs.command_long_encode(1, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 0, 0, 0, 0, 0))
            rig.tick()  # handled after this tick (the GCS failsafe: heartbeats stop here)
            handled = rig.time_us - PERIOD_US
            if stop == "gcs failsafe":
                rig.run_until(handled + 500_000 + 3 * PERIOD_US)
                handled = polled.failsafe_at if polled.failsafe_at is not None else handled
                if polled.failsafe_at is None:
                    problems.append("the GCS failsafe did not trip")
            rig.run_until(rig.time_us + 20 * PERIOD_US)
        problems += _stopped_by(rig, handled + 1, handled + PERIOD_US)
        if rig.ctrl.exploration.running:
            problems.append("still exploring")
        problems += [f"poll raised: {e}" for e in polled.errors]
        res.check(problems, f"seed {seed}/{i} {stop} at {handled} us")


# --- findings 3 and 4 ----------------------------------------------------------------------------

@register("activation_worst_case", small=1, large=5, unit="episodes",
          what="largest legal map + extreme planner metadata activated while driving: old policy drives until "
               "ready, every tick answered, no step over the period, no FAULT")
def activation_worst_case(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    data = largest_legal_map_policy()
    new_id = fmt.load_policy(data).policy_id
    with tempfile.TemporaryDirectory(prefix="qnav-worst-") as tmp:
        path = Path(tmp) / "worst.qtab"
        path.write_bytes(data)
        for i in trials(count, progress):
            rng, rig = _sector_rig(seed * 7919 + 12000 + i)
            problems: list[str] = []
            with rig:
                _drive_to(rig, _fault_time(rng), "at the activation", problems)
                old_id = _policy_id(rig)
                early = rig.ctrl.begin_activation(str(path))  # while driving: refused now, with the reason
                if not (isinstance(early, tuple) and not early[0] and early[1]) or _policy_id(rig) != old_id:
                    problems.append(f"while DRIVING: {early}, expected a refusal with a reason")
                if not rig.ctrl.set_mode(Mode.HOLD)[0]:  # stopped, armed: where the 37 s freeze was measured
                    problems.append("setup: Hold refused")
                rig.tick()
                t0 = rig.time_us
                pending = rig.ctrl.begin_activation(str(path))
                result = pending if isinstance(pending, tuple) else None
                while result is None and rig.time_us < t0 + 600_000_000:
                    if _policy_id(rig) != old_id:
                        problems.append("the policy changed before its activation finished")
                        break
                    rig.tick()  # raises if a tick goes unanswered
                    result = pending.result()  # type: ignore[union-attr]
                ticks = (rig.time_us - t0) // PERIOD_US
                rig.run_until(rig.time_us + 5 * PERIOD_US)
                if result is None:
                    problems.append("no verdict within 600 s of sim time")
                elif result[0] and _policy_id(rig) != new_id:
                    problems.append("accepted, but another policy is active")
                elif not result[0] and not result[1]:
                    problems.append("refused without a reason")
                fault = _first_fault(rig, t0)
                if fault is not None:
                    problems.append(f"FAULT during the activation: {fault.cause}")
                problems += _max_step_problem(rig, res)
            res.figures["ticks_driven_while_building"] = max(res.figures.get("ticks_driven_while_building", 0), ticks)
            res.check(problems, f"seed {seed}/{i} activation at {t0} us -> {result}")


@register("planner_worst_case", small=1, large=10, unit="episodes",
          what="extreme legal planner metadata, 3 discs + 2 movers: search off the tick, no step over the period, "
               "no FAULT")
def planner_worst_case(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    from ground_station.lab.nav.scenario import episodes as nav_episodes
    from sim_bridge.obstacles import ObstacleLayer

    gm = paper10()
    candidates = iter(nav_episodes(gm, 4 * count, seed + 13000, 3, 2))
    i = 0
    while i < count:
        ep = next(candidates)
        # even trials: the search at its largest; odd: the largest per-tick observation (a 1 m margin,
        # which also hides most obstacles from the planner: it may not search at all then)
        margin = 150 if i % 2 == 0 else 1000
        data = _sector_variant({**EXTREME_PLANNER, "margin_mm": margin})
        problems: list[str] = []
        start = (ep.start[0] / 1000.0, ep.start[1] / 1000.0, ep.start[2])
        goals = [(round(x), round(y)) for x, y in ep.waypoints]
        with LockstepRig(gm.occ, fmt.load_policy(data), start, goals, seed=ep.seed) as rig:
            rig.plant.obstacles = ObstacleLayer(rig.plant.world, ep.discs, ep.movers)
            while rig.time_us < 40_000_000 and not rig.runner.done.is_set():
                rig.tick()  # raises if a tick goes unanswered
            work = rig.ctrl.background
        planner = rig.ctrl.driver.local[0] if rig.ctrl.driver is not None else None  # type: ignore[attr-defined]
        plans = planner.plans if planner is not None else 0
        if plans == 0 and margin == 150:
            res.figures["episodes_without_a_search"] = res.figures.get("episodes_without_a_search", 0) + 1
            continue  # nothing was in the way on this route: not a trial of the search, take the next
        if plans and not work.runs:
            problems.append(f"{plans} searches, none on the background: they ran in the tick")
        fault = _first_fault(rig, 0)
        if fault is not None:
            problems.append(f"FAULT: {fault.cause}")
        problems += _max_step_problem(rig, res)
        res.figures["plans"] = res.figures.get("plans", 0) + plans
        res.figures["longest_search_us"] = max(res.figures.get("longest_search_us", 0), work.max_cpu_ns // 1000)
        res.check(problems, f"seed {seed}/{i} {ep.map} margin {margin} mm, {plans} searches, {rig.runner.result}")
        i += 1
        if progress is not None:
            progress.update(1)


# --- finding 5 -----------------------------------------------------------------------------------

@register("param_save_full_disk", small=2, large=20, unit="trials",
          what="PARAM_SET on a full disk: echoed, ERROR STATUSTEXT 'lost at reboot', not in a reload; next save sticks")
def param_save_full_disk(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    from firmware_py.control.controller import Controller
    from firmware_py.mavlink import params as params_module
    from firmware_py.mavlink.node import MavNode
    from firmware_py.mavlink.params import ParamStore
    from firmware_py.mavlink.signing import Signing
    from ground_station.lab.faults.hostile_holes import _dialect

    m = _dialect()
    rng = random.Random(seed * 7919 + 14000)
    real_write = params_module.atomic_write  # type: ignore[attr-defined]

    def full(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device")

    for i in trials(count, progress):
        name, value = rng.choice(((b"GOAL_TOL_MM", rng.randrange(100, 900)), (b"SPEED_SCALE", rng.randrange(20, 100))))
        problems: list[str] = []
        with tempfile.TemporaryDirectory(prefix="qnav-params-") as tmp:
            node = MavNode(Controller(), ParamStore(Path(tmp)), Signing(None))
            node.boot(0)
            gcs = m.MAVLink(None, *GCS)
            parser = m.MAVLink(None)

            def send(msg, now_us: int, node=node, gcs=gcs, parser=parser) -> list:
                got = parser.parse_char(bytes(msg.pack(gcs)))
                return node.handle(got, now_us) + node.tick(now_us)

            with mock.patch.object(params_module, "atomic_write", full):
                replies = send(gcs.param_set_encode(1, 1, name, value, 6), 1000)
            echo = [r.param_value for r in replies if r.get_type() == "PARAM_VALUE"]
            errors = "".join(r.text for r in replies if r.get_type() == "STATUSTEXT"
                             and r.severity == m.MAV_SEVERITY_ERROR)
            if echo != [value]:
                problems.append(f"echo {echo}, expected [{value}]")
            if "lost at reboot" not in errors:
                problems.append(f"no ERROR STATUSTEXT about the lost save (got {errors!r})")
            reloaded = ParamStore(Path(tmp))
            reloaded.load()
            if reloaded.get(name.decode()) == value:
                problems.append("the value was saved although the disk was full")
            assert params_module.atomic_write is real_write  # type: ignore[attr-defined]
            send(gcs.param_set_encode(1, 1, name, value + 1, 6), 2000)
            reloaded.load()
            if reloaded.get(name.decode()) != value + 1:
                problems.append(f"after space came back the save did not stick ({reloaded.get(name.decode())})")
            if node.handler_errors:
                problems.append(f"handler exceptions: {node.handler_errors}")
        res.check(problems, f"seed {seed}/{i} {name.decode()}={value}")


# --- finding 7 -----------------------------------------------------------------------------------

def _bad_goal(rng: random.Random, gm) -> tuple[int, int, str]:
    """(x, y) mm of a goal the robot must refuse, and the word its reason must hold."""
    side_x, side_y = gm.width * 500, gm.height * 500
    kind = rng.choice(("outside", "wall", "near"))
    if kind == "outside":
        x = rng.choice((-rng.randrange(50, 3000), side_x + rng.randrange(50, 3000)))
        return x, rng.randrange(side_y), "of the map"
    walls = [(c, r) for r in range(gm.height) for c in range(gm.width) if gm.occ[r, c]]
    c, r = rng.choice(walls)
    x, y = robot_spec.cell_center_mm(c, r, gm.height)
    if kind == "wall":
        return x + rng.randrange(-200, 201), y + rng.randrange(-200, 201), "wall"
    # beside a wall cell, in a free neighbour, within the robot's radius of the wall's face
    for dc, dr in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        if 0 <= c + dc < gm.width and 0 <= r + dr < gm.height and not gm.occ[r + dr, c + dc]:
            gap = rng.randrange(10, robot_spec.ROBOT_RADIUS_MM - 10)
            return x + dc * (250 + gap), y - dr * (250 + gap), "wall"
    return x, y, "wall"


@register("goal_refusals", small=6, large=60, unit="goals",
          what="goals outside the map / in a wall / nearer a wall than the robot radius refused with the reason "
               "(3 MAVLink ways); VALID readings above the maximum not used")
def goal_refusals(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    # the rule the controller applies to readings (control/io.py)
    from firmware_py.layout import DEFAULT as LAYOUT

    rng = random.Random(seed * 7919 + 15000)
    gm = paper10()
    for i in trials(count, progress):
        x, y, word = _bad_goal(rng, gm)
        # a VALID reading beyond the sensor's maximum is not a reading (finding 7's second half)
        beyond = robot_spec.RANGE_MAX_MM + rng.randrange(1, 2096)
        n = len(LAYOUT.max_ranges_mm)
        valid_beyond = LAYOUT.plausible([beyond] * n, [robot_spec.RANGE_VALID] * n) != [robot_spec.RANGE_INVALID] * n
        way = ("SET_POSITION_TARGET_LOCAL_NED", "DO_REPOSITION", "MISSION_ITEM_INT")[i % 3]
        problems = [f"a VALID {beyond} mm reading kept as VALID"] if valid_beyond else []
        _, rig = _sector_rig(seed * 7919 + 15000 + i, with_goal=False)
        with rig:
            polled = _PolledNode(rig, 120_000)
            m, gcs = polled.m, polled.m.MAVLink(None, *GCS)
            def send(msg, gcs=gcs, polled=polled) -> None:
                polled.inbox.put(bytes(msg.pack(gcs)))

            send(gcs.command_long_encode(1, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
            rig.run_until(3 * PERIOD_US)
            n_m, e_m = y / 1000.0, x / 1000.0  # LOCAL_NED: north = world y, east = world x
            if way == "SET_POSITION_TARGET_LOCAL_NED":
                send(gcs.set_mode_encode(1, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(Mode.GUIDED)))
                send(gcs.set_position_target_local_ned_encode(0, 1, 1, m.MAV_FRAME_LOCAL_NED, 0b110111111000,
                                                              n_m, e_m, 0, 0, 0, 0, 0, 0, 0, 0, 0))
            elif way == "DO_REPOSITION":
                send(gcs.command_int_encode(1, 1, m.MAV_FRAME_LOCAL_NED, m.MAV_CMD_DO_REPOSITION, 0, 0, -1,
                                            m.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, 0,
                                            round(n_m * 1e4), round(e_m * 1e4), 0))
            else:
                send(gcs.mission_count_encode(1, 1, 1, 0))
                rig.tick()
                send(gcs.mission_item_int_encode(1, 1, 0, m.MAV_FRAME_LOCAL_NED, m.MAV_CMD_NAV_WAYPOINT, 0, 1,
                                                 0, 0, 0, 0, round(n_m * 1e4), round(e_m * 1e4), 0, 0))
            rig.run_until(rig.time_us + 10 * PERIOD_US)
            texts = " | ".join(polled.texts)
            state = rig.ctrl.state
        if state == CtrlState.DRIVING or any(c[1] or c[2] for c in rig.commands):
            problems.append(f"the robot drove toward ({x}, {y}) mm")
        if rig.ctrl.goal is not None:
            problems.append(f"goal {rig.ctrl.goal} accepted")
        if word not in texts.replace(" | ", ""):  # long reasons come in STATUSTEXT chunks
            problems.append(f"the reason does not say '{word}': {texts}")
        problems += [f"poll raised: {e}" for e in polled.errors]
        res.check(problems, f"seed {seed}/{i} {way} ({x}, {y}) mm")
