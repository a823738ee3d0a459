"""The tick's side of the sector kind's local planner (`PlannedTarget`): each tick it decides
whether anything is in the way (cheap), posts the question (pose, waypoint, a copy of the memory)
to `firmware_py.background` and steers by the latest answer, at half speed once that (or, before
the first, the moment the way became blocked) is `PLAN_SLOW_US` old, stopped at `PLAN_STOP_US`;
when the search finds no way the recoveries run (`PlannedTarget`'s docstring lists them in order).
The schedule (the answer of tick k steers tick k+1 in lockstep HIL and the twin) and the
controller's part in "no route": docs/architecture.md, "Local re-planning on the robot".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from firmware_py import robot_spec
from firmware_py.background import Background
from firmware_py.kinds.sector import decide
from firmware_py.kinds.sector.config import LocalPlannerConfig
from firmware_py.kinds.sector.memory import ObstacleMemory
from firmware_py.kinds.sector.planner import LocalPlanner, refuge_mm
from firmware_py.mapdata import OccupancyGrid

PLAN_SLOW_US = 300_000  # an answer older than this (controller clock): half speed ...
PLAN_STOP_US = 1_000_000  # ... and none this old (or none for this long): stop


@dataclass(frozen=True)
class PlanAnswer:
    """The worker's answer to one question: where to steer from the pose asked about."""

    generation: int  # PlannedTarget.reset() count when asked (older answers are for another waypoint)
    waypoint: tuple[int, int]
    asked_us: int  # the controller clock at the question
    target: tuple[float, float]
    detouring: bool
    whole_map: bool = False  # a global re-plan's answer
    blocked: bool = False  # no way from the pose to the waypoint (in the window searched)
    no_route: bool = False  # none over the whole map either
    route_mm: float = 0.0  # the planned way's length from the pose asked about
    held: bool = False  # the whole map's route is closed ahead: stand while it is held to
    refuge: tuple[int, int] | None = None  # with no_route: where to stand aside (LocalPlanner.refuge)
    # with no_route: none either over what stood still through the round's wait (ObstacleMemory.standing_by):
    # what moved did not close the way
    still_closed: bool = False
    # with no_route and not still_closed: where to steer now on the route without what came in during the
    # round's wait (APPROACH), if it has one
    approach_target: tuple[float, float] | None = None


@dataclass(frozen=True)
class RefugeAnswer:
    """The worker's answer while the robot gives way: where to steer now on the way to the refuge."""

    generation: int
    asked_us: int
    target: tuple[float, float]


# PlannedTarget's recovery modes, in the order they follow one another (see PlannedTarget)
LOCAL, WAIT, GLOBAL, GIVE_WAY, BACKUP, CLEAR, NO_ROUTE = (
    "local", "wait", "global", "give way", "backup", "clear", "no route")
ROUTE_SWITCH_MM = 1000  # a whole-map answer this much longer than the route followed is another route
GIVE_WAY_US = 15_000_000  # at most this long driving to the place where the robot stands aside
REFUGE_REACHED_MM = 100  # ... which it has reached this near


class PlannedTarget:
    """The tick's side of the local planner (module docstring): one per drive of a sector policy.

    Recoveries, when the window's search finds no way to the waypoint (nav2's recovery behaviours,
    in this order, all on the controller clock):

    1. WAIT `wait_us` (in round r, r x `wait_us`), stopped: a mover may step aside; the window's
       search goes on, and a way found ends the recovery.
    2. GLOBAL: the points remembered now are pinned (`route_memory_us`) and the search covers the
       whole map (another door, another aisle); a route is followed to the waypoint. With none, but
       one without what came in during the round's wait (`ObstacleMemory.seen_by`: a person walked into
       the only corridor) and one over what stood still (`still_closed` below), APPROACH: that route
       is driven for up to `approach_us` from the search (the person walks on ahead of the robot or
       steps aside where there is room, and readings see through where it stood); then 3. The blocked
       bench's wrong "no route" were people in a maze's corridor seen from afar (docs/results.md
       section 6).
    3. No route: BACKUP `backoff_us` (the driver reverses when the rear is clear), CLEAR the
       obstacle layer round the robot (pinned points `window_mm` or more away stay: what closed the
       whole map's routes out there), then 1. again. In a round where something came up to the
       robot, GIVE_WAY first: drive (at most `GIVE_WAY_US`) to the nearest place off the line the
       nearest body walks (`LocalPlanner.refuge`: a side corridor, a room's corner) and stand there
       (1. again; the way back is the whole map's route); with no such place within
       `REFUGE_SEARCH_MM`, BACKUP. The round spent standing aside does not count.
    4. After `max_rounds` global searches without a route: NO_ROUTE, stopped, `no_route` says why
       (the controller reports it and ends the mission). A round does not count (up to 3 x
       `max_rounds` rounds in all) when it was a moving scene (its wait saw more than
       `moving_points` new points within `MOVING_NEAR_MM`, and the whole map would be open without
       what moved since: `ObstacleMemory.standing_by`), or when a remembered point came within the
       robot's radius + `veto_mm` (the guard never steps that close: it came to the robot).

    With a recovery table (`decisions`: `decide.RecoveryTable`, a policy's `recovery_table`) the
    table decides, every `decide.DECIDE_US` of a wait, whether to wait on or re-plan over the whole
    map (instead of 1.'s r x `wait_us`), and, when a round's search found no route, whether to try
    another round, give way or say "no route" (instead of 3.'s choice and 4.'s counting); 4.'s bound
    of 3 x `max_rounds` rounds stays.

    A waypoint beyond `max_plan_mm` is driven at without planning while the map leaves the straight
    line to it free (looked at off the tick); once it does not, the tick's side goes to GLOBAL at
    once: the whole map's route leads back.
    """

    def __init__(self, grid: OccupancyGrid, cfg: LocalPlannerConfig, work: Background,
                 radius_mm: int = robot_spec.ROBOT_RADIUS_MM, decisions: decide.RecoveryTable | None = None) -> None:
        self.cfg = cfg
        self.decisions = decisions  # the learnt recovery decisions (decide), or None: the hand-written rules
        self._decided_us = 0  # the last waiting decision (decide.EV_WAIT)
        self.radius_mm = radius_mm  # the body's (firmware_py.layout)
        self.planner = LocalPlanner(grid, cfg, radius_mm)  # used by the worker only, after construction
        self.work = work
        self._generation = 0
        self._worker_generation = 0
        self._answer: PlanAnswer | None = None
        self._active: tuple[int, int] | None = None
        self._active_since_us = 0
        self.detouring = False  # the last target was not the waypoint
        self.mode = LOCAL
        self._mode_since_us = 0
        self._rounds = 0  # global searches without a route for this waypoint (in a still scene)
        self._all_rounds = 0  # ... and in all
        self._added_at_wait = 0  # memory.added when the last wait began ...
        self._round_since_us = 0  # ... and when (the points first seen since moved in during the round)
        self._still_planner: LocalPlanner | None = None  # the worker's, for PlanAnswer.still_closed
        self._came_up = False  # something came up to the robot during this round (_recovering)
        self.reverse = False  # this tick: back off (BACKUP)
        self.no_route = ""  # why the waypoint cannot be reached (NO_ROUTE), else ""
        self._refuge: tuple[int, int] = (0, 0)  # where the robot stands aside (GIVE_WAY)
        self._refuge_answer: RefugeAnswer | None = None  # the worker's, while giving way
        self.give_ways = 0  # times the robot stood aside (telemetry / benchmarks)
        self._aside = False  # it stands aside now: off the route the waypoints follow (_recovering)
        self.global_plans = 0  # global re-plans started (telemetry / benchmarks)
        # whole-map routes taken: the first answer of a round with a route, and each switch to a way
        # round longer by ROUTE_SWITCH_MM (the route followed closed; benchmarks count progress anew)
        self.routes_taken = 0
        self._followed_mm = 0.0  # the whole-map route's length at the last answer followed
        self._round_taken = 0
        self.route_mm = 0.0  # the latest answer's planned way to the waypoint (benchmarks' progress)
        # (generation, waypoint, the map leaves the line to it free): a far waypoint's sight line (_look)
        self._far_sight: tuple[int, tuple[int, int], bool] | None = None

    @property
    def plans(self) -> int:
        return self.planner.plans + (self._still_planner.plans if self._still_planner is not None else 0)

    def reset(self) -> None:
        """A new waypoint (mission item): drive straight until something is in the way."""
        self._generation += 1
        self._answer = None
        self._active = None
        self.detouring = False
        self.mode, self._rounds, self._all_rounds, self.reverse, self.no_route = LOCAL, 0, 0, False, ""
        self._aside = False

    def _enter(self, mode: str, now_us: int) -> None:
        self.mode, self._mode_since_us = mode, now_us

    def _begin_round(self, now_us: int, memory: ObstacleMemory, came_up: bool) -> None:
        """A round of recoveries begins with its wait: what is added from now tells a moving scene."""
        self._added_at_wait, self._round_since_us, self._came_up = memory.added, now_us, came_up
        self._decided_us = now_us

    def _choose(self, state: int) -> int:
        """The recovery table's action in `state` (a trainer overrides this to explore)."""
        assert self.decisions is not None
        return self.decisions.choose(state)

    def _wait_over(self, now_us: int, x: float, y: float, memory: ObstacleMemory) -> bool:
        """Whether this WAIT ends in a whole-map search now."""
        cfg = self.cfg
        waited = now_us - self._mode_since_us
        if self.decisions is None:  # the hand-written rule: r x wait_us in round r
            return waited >= cfg.wait_us * min(self._all_rounds + 1, cfg.max_rounds)
        if waited >= 3 * cfg.max_rounds * cfg.wait_us:
            return True  # the bound: no table holds the robot for ever
        if now_us - self._decided_us < decide.DECIDE_US:
            return False
        self._decided_us = now_us
        near = 0 if memory.within(x, y, self.radius_mm + cfg.veto_mm) else (
            1 if memory.within(x, y, decide.MOVING_NEAR_MM) else 2)
        moving = memory.added - self._added_at_wait > cfg.moving_points
        return self._choose(decide.wait_state(waited, self._all_rounds, near, moving)) == decide.REPLAN

    def target(self, now_us: int, x: float, y: float, waypoint: tuple[int, int],
               memory: ObstacleMemory) -> tuple[float, float, int]:
        """(x, y) mm to steer to this tick and the speed in percent (100, 50 or 0)."""
        wx, wy = waypoint
        self.reverse = False
        if self.mode == NO_ROUTE:
            return float(wx), float(wy), 0
        if self.mode == GIVE_WAY:
            return self._giving_way(now_us, x, y, waypoint, memory)
        if self.mode == BACKUP:
            if now_us - self._mode_since_us < self.cfg.backoff_us:
                self.reverse = True
                return float(wx), float(wy), 0
            memory.clear(now_us, x, y, self.cfg.window_mm)  # CLEAR: the next tick asks on what is seen again
            self._enter(CLEAR, now_us)
            return float(wx), float(wy), 0
        if self.mode == CLEAR:
            self._enter(WAIT, now_us)
            self._begin_round(now_us, memory, False)
        whole_map = self.mode == GLOBAL
        if not whole_map:  # in GLOBAL it stays the route's (a tick without an answer followed: the last one's)
            self.route_mm = math.hypot(wx - x, wy - y)
        if self.mode == LOCAL:
            if math.hypot(wx - x, wy - y) > self.cfg.max_plan_mm:
                self.detouring = False  # far: driven at without planning (LocalPlanner.target) ...
                gen = self._generation
                sight = self._far_sight
                if sight is not None and sight[:2] == (gen, waypoint) and not sight[2]:
                    # ... unless the map's walls stand between: a straight drive at a waypoint metres
                    # away in a maze stalls at the first wall; the whole map's route leads back
                    memory.pin(now_us)
                    self.global_plans += 1
                    self._enter(GLOBAL, now_us + 1)
                    return float(wx), float(wy), 0
                self.work.post(self, lambda: self._look(gen, x, y, waypoint))
                return float(wx), float(wy), 100
            if self._active != waypoint:
                if not memory.points or not self.planner._in_way(x, y, wx, wy, memory):
                    self.detouring = False
                    return float(wx), float(wy), 100
                self._active, self._active_since_us = waypoint, now_us
            # what the robot goes round is kept while it does (unless a reading sees through it): a
            # box forgotten once out of view sent the route back to it, and the robot turned to and fro
            memory.pin(now_us)
        gen, snap, since = self._generation, memory.snapshot(born=whole_map), self._round_since_us
        self.work.post(self, lambda: self._solve(gen, now_us, x, y, waypoint, snap, whole_map, since))
        ans = self._answer
        if ans is not None and (ans.generation != gen or ans.waypoint != waypoint):
            ans = None
        if ans is not None and (ans.whole_map != whole_map or ans.asked_us < self._mode_since_us):
            ans = None  # asked before this mode began: not an answer to its question
        if self.mode in (WAIT, GLOBAL):
            if self.mode == WAIT and not self._came_up:
                self._came_up = memory.within(x, y, self.radius_mm + self.cfg.veto_mm)
            return self._recovering(now_us, x, y, waypoint, ans, memory)
        if ans is not None and ans.blocked:
            self._enter(WAIT, now_us)
            self._begin_round(now_us, memory, False)
            return float(wx), float(wy), 0
        if ans is None:
            # nothing answered for this waypoint yet (the tick it became blocked, in lockstep and the
            # twin): toward it, the motion guard still vetoing; how long counts from then
            self.detouring = False
            age, tx, ty = now_us - self._active_since_us, float(wx), float(wy)
        else:
            self.detouring = ans.detouring
            age, (tx, ty) = now_us - ans.asked_us, ans.target
            self.route_mm = ans.route_mm
        return tx, ty, self._speed(age)

    def _speed(self, age_us: int) -> int:
        """Full speed while the answer steered by is at most PLAN_SLOW_US old, half up to PLAN_STOP_US,
        then none (counted as stale ticks)."""
        return 100 if age_us <= PLAN_SLOW_US else 50 if age_us <= PLAN_STOP_US else 0

    def _recovering(self, now_us: int, x: float, y: float, waypoint: tuple[int, int], ans: PlanAnswer | None,
                    memory: ObstacleMemory) -> tuple[float, float, int]:
        """WAIT and GLOBAL (the class docstring's steps 1, 2 and 4)."""
        cfg = self.cfg
        wx, wy = waypoint
        if self.mode == WAIT:  # a waypoint beyond max_plan_mm has no window search (LocalPlanner.target): its
            # answer is no opening, the wait runs its course (it ended at once: 3 rounds in 2 s, "no route")
            near = math.hypot(wx - x, wy - y) <= cfg.max_plan_mm
            if ans is not None and not ans.blocked and near and self._aside:
                # the way opened from the refuge: back to the waypoint by the whole map's route (a straight
                # drive from a side corridor meets the wall between)
                self._aside = False
                self.global_plans += 1
                self._enter(GLOBAL, now_us + 1)
                return float(wx), float(wy), 0
            if ans is not None and not ans.blocked and near:
                self._enter(LOCAL, now_us)  # the way opened (a mover stepped aside)
                self.detouring = ans.detouring
                return ans.target[0], ans.target[1], 100
            if self._wait_over(now_us, x, y, memory):
                memory.pin(now_us)
                self.global_plans += 1
                self._enter(GLOBAL, now_us + 1)  # the next tick asks over the whole map
            return float(wx), float(wy), 0
        if ans is None:  # GLOBAL, no answer yet: stand still while the whole map is searched
            return float(wx), float(wy), 0
        if ans.approach_target is not None and now_us - self._mode_since_us < cfg.approach_us:  # (no_route)
            self.detouring = True  # APPROACH (step 2): toward what came in, on the route without it
            return ans.approach_target[0], ans.approach_target[1], self._speed(now_us - ans.asked_us)
        if ans.no_route:
            self._all_rounds += 1
            # a moving scene: new points came near while the robot waited, and without what moved the
            # way would be open (a mover walking past the robot while a box closes the door: still)
            moving = memory.added - self._added_at_wait > cfg.moving_points and not ans.still_closed
            if self.decisions is not None:
                act = self._choose(decide.round_state(self._rounds, self._all_rounds, self._came_up, moving,
                                                      ans.refuge is not None))
                if not moving and not self._came_up:
                    self._rounds += 1
                say_no = act == decide.NO_ROUTE or self._all_rounds >= 3 * cfg.max_rounds
                give_way = act == decide.GIVE_WAY
            else:
                if not moving and not self._came_up:
                    self._rounds += 1  # a still scene: what closes the way stays
                say_no = self._rounds >= cfg.max_rounds or self._all_rounds >= 3 * cfg.max_rounds
                give_way = self._came_up
            if say_no:
                self._enter(NO_ROUTE, now_us)
                self.no_route = f"no route to ({wx},{wy})"  # <= 50 characters with the item
            elif ans.refuge is not None and give_way:
                self._refuge = ans.refuge
                self._generation += 1  # the refuge's questions are not the waypoint's
                # what stands at the robot walks: seen again or forgotten, not kept a minute (a box
                # farther off stays pinned, or the robot goes round and round)
                memory.unpin_near(x, y, refuge_mm(self.radius_mm))
                self._enter(GIVE_WAY, now_us)
            else:
                self._enter(BACKUP, now_us)
            return float(wx), float(wy), 0
        self.detouring = ans.detouring
        if ans.held:  # the route closed ahead: stand while the planner holds to it (LocalPlanner._plan)
            return float(wx), float(wy), 0
        if self._round_taken != self.global_plans:  # the first route of this round of recoveries
            self._round_taken = self.global_plans
            self.routes_taken += 1
        elif ans.route_mm > self._followed_mm + ROUTE_SWITCH_MM:
            self.routes_taken += 1  # the route closed and the search found another way round
        self.route_mm = self._followed_mm = ans.route_mm
        return ans.target[0], ans.target[1], self._speed(now_us - ans.asked_us)

    def _giving_way(self, now_us: int, x: float, y: float, waypoint: tuple[int, int],
                    memory: ObstacleMemory) -> tuple[float, float, int]:
        """GIVE_WAY (the class docstring's step 3): to the refuge, then WAIT there."""
        wx, wy = waypoint
        gen, snap, refuge = self._generation, memory.snapshot(), self._refuge
        self.work.post(self, lambda: self._solve_refuge(gen, now_us, x, y, refuge, snap))
        ans = self._refuge_answer
        if ans is not None and (ans.generation != gen or ans.asked_us < self._mode_since_us):
            ans = None
        there = math.hypot(refuge[0] - x, refuge[1] - y) <= REFUGE_REACHED_MM
        if there or now_us - self._mode_since_us > GIVE_WAY_US:
            self.give_ways += 1
            self._aside = True
            self._generation += 1  # the waypoint's questions again, from here
            self._enter(WAIT, now_us)
            # a round spent standing aside for a mover is not a still scene's (the refuge may not see
            # the way it closed)
            self._begin_round(now_us, memory, True)
            return float(wx), float(wy), 0
        if ans is None:
            return float(wx), float(wy), 0  # the first answer comes next tick
        self.detouring = True
        return ans.target[0], ans.target[1], self._speed(now_us - ans.asked_us)

    def _solve_refuge(self, generation: int, asked_us: int, x: float, y: float, refuge: tuple[int, int],
                      memory: ObstacleMemory) -> None:
        """The worker's part while giving way: the way from the pose asked about to the refuge."""
        p = self.planner
        if generation != self._worker_generation:
            p.reset()
            self._worker_generation = generation
        target = p.target(x, y, refuge, memory, True, asked_us)
        self._refuge_answer = RefugeAnswer(generation, asked_us, target)

    def _look(self, generation: int, x: float, y: float, waypoint: tuple[int, int]) -> None:
        """The worker's part for a far waypoint: whether the map lets the robot see it."""
        self._far_sight = (generation, waypoint, self.planner.map_sight(x, y, *waypoint))

    def _solve(self, generation: int, asked_us: int, x: float, y: float, waypoint: tuple[int, int],
               memory: ObstacleMemory, whole_map: bool = False, round_since_us: int = 0) -> None:
        """The worker's part: `LocalPlanner.target` for the pose asked about (with no route: where to
        stand aside, and whether what stood still through the round's wait closes the way)."""
        if generation != self._worker_generation:
            self.planner.reset()
            self._worker_generation = generation
        p = self.planner
        tx, ty = p.target(x, y, waypoint, memory, whole_map, asked_us)
        # no route: where the robot might stand aside, should something have come up to it (GIVE_WAY)
        refuge = p.refuge(x, y, memory) if p.no_route else None
        still_closed, approach_target = (self._closed_before(x, y, waypoint, memory, round_since_us, asked_us)
                                      if p.no_route else (False, None))
        self._answer = PlanAnswer(generation, waypoint, asked_us, (tx, ty), p.detouring, whole_map, p.blocked,
                                  p.no_route, p.route_mm, p.held, refuge, still_closed, approach_target)

    def _closed_before(self, x: float, y: float, waypoint: tuple[int, int], memory: ObstacleMemory,
                       since_us: int, asked_us: int) -> tuple[bool, tuple[float, float] | None]:
        """Whether the whole map has no route over what stood still since `since_us` either (the
        worker's, after a whole-map search said no route), and where to steer on the route over
        everything seen by then (what came in since left out: APPROACH), if it has one."""
        seen = memory.seen_by(since_us)
        if len(seen.points) == len(memory.points):
            return True, None  # nothing came in: the search just made was over the same points
        q = self._still_planner
        if q is None:
            q = self._still_planner = self.planner.sharing_map()
        # approached only where what came in during the wait closes the way: what was there before stays
        # (standing_by leaves out a box's points near a person walking beside it, or near new squares of
        # its own readings' jitter; driving at such a box held the robot in HIL until the stall watch
        # ended the mission instead of "no route")
        q.reset(points=True)
        target = q.target(x, y, waypoint, seen, True, asked_us)
        if not q.no_route:
            return False, target  # standing_by holds fewer of the same points: open there too
        q.reset(points=True)
        q.target(x, y, waypoint, memory.standing_by(since_us), True, asked_us)
        return q.no_route, None
