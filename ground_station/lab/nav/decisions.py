"""Which decision of the sector kind's recoveries ends each failed episode (issue 47, step 1).

`trace(episodes, maps, controller)` rolls each episode out on the twin (`nav.planned.rollout`)
with a `TracingTarget`: the controller's own `PlannedTarget` (hand-written recoveries or the
learnt recovery table) that also counts, per control period, the recovery mode it was in and
whether it asked to stand still, and logs every mode change with the round counts. A failed
episode is given the decision that ended it (`classify`):

* `no_route`: the robot said "no route" (`declared:still` = `max_rounds` still rounds,
  `declared:cap` = 3 x `max_rounds` rounds in all; `+gave_way` when it stood aside first);
* a timeout or loop, by where the last `TAIL_PERIODS` periods went: `waiting` (WAIT, a whole-map
  route held or not yet answered), `giving_way`, `backing_off` (BACKUP, CLEAR), `detour` (driving a
  whole-map route), `local` (driving on the window's sub-goals or straight at the waypoint:
  the table, guard and monitor);
* `collision`, by the mode it happened in.

Each row also says whether the episode ended in a **stand-off** (`standoff`): a mover's body nearer than
`STANDOFF_GAP_MM` to the robot's for at least 90 % of the last `STANDOFF_PERIODS` periods (a mover
that does not give way stands while a step would overlap the robot: in a one-cell corridor or a
dead end neither moves again); and whether it was a **sandwich** (`sandwich`): two movers' bodies
that near for as long, the robot pinned between them (no decision of the robot's ends it: two that
do not give way stand for each other's side of it for ever, so only not being there helps).

And whether, at the last whole-map "no route" of the episode, a **later waypoint was reachable**
(`later_reachable`): the same search over the same memory towards the next two waypoints of the
episode and its goal, the way a skip of the unreachable waypoint would go (a mover parked on the
waypoint in a dead end closes that waypoint, not the way on).

`qnav bench decisions` prints the counts (ground_station/lab/bench/decisions.py).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from firmware_py import robot_spec
from firmware_py.kinds.sector.memory import ObstacleMemory
from firmware_py.kinds.sector.recoveries import (
    BACKUP,
    CLEAR,
    GIVE_WAY,
    GLOBAL,
    LOCAL,
    WAIT,
    PlanAnswer,
    PlannedTarget,
)
from ground_station.lab.nav.controllers import NavController
from ground_station.lab.nav.scenario import Episode, rollout_arrays
from ground_station.maps import GridMap
from sim_bridge.obstacles import YIELD_MARGIN_MM

TAIL_PERIODS = 400  # the loop rule's window (episodes.STALL_STEPS): where a timeout's last stretch went
STANDOFF_PERIODS = 200  # 10 s: an episode's end looked at for a stand-off
STANDOFF_GAP_MM = YIELD_MARGIN_MM  # a mover's body nearer the robot's than this: nearer than a yielding one comes


@dataclass
class Trace:
    """Per-period mode counts of one episode (mode, or 'stand' for a mode asking speed 0) and the
    mode changes (period, mode, still rounds, all rounds, came_up)."""

    modes: list[str] = field(default_factory=list)
    changes: list[tuple[int, str, int, int, bool]] = field(default_factory=list)
    later_open: bool | None = None  # at the last whole-map "no route": a later waypoint reachable (None: none said)


class TracingTarget(PlannedTarget):
    """A mixin over the controller's `PlannedTarget` (`traced`) that records a `Trace`."""

    trace: Trace
    later: list[tuple[int, int]]  # the episode's waypoints, the goal last (`later_open`)

    def _enter(self, mode: str, now_us: int) -> None:
        super()._enter(mode, now_us)
        self.trace.changes.append((len(self.trace.modes), mode, self._rounds, self._all_rounds, self._came_up))

    def target(self, now_us: int, x: float, y: float, waypoint: tuple[int, int],
               memory: ObstacleMemory) -> tuple[float, float, int]:
        tx, ty, speed = super().target(now_us, x, y, waypoint, memory)
        mode = self.mode
        if mode in (LOCAL, GLOBAL) and speed == 0:
            mode = "stand"
        self.trace.modes.append(mode)
        return tx, ty, speed

    def _recovering(self, now_us: int, x: float, y: float, waypoint: tuple[int, int], ans: PlanAnswer | None,
                    memory: ObstacleMemory) -> tuple[float, float, int]:
        if ans is not None and ans.no_route and self.mode == GLOBAL:
            self.trace.later_open = self.later_open(now_us, x, y, waypoint, memory)
        return super()._recovering(now_us, x, y, waypoint, ans, memory)

    def later_open(self, now_us: int, x: float, y: float, waypoint: tuple[int, int], memory: ObstacleMemory) -> bool:
        """Whether the whole map has a route from (x, y) over `memory` to one of the next two waypoints
        after `waypoint` or the goal (a planner of its own on the same map: the robot's is untouched)."""
        if waypoint not in self.later:
            return False
        k = self.later.index(waypoint)
        q = self.planner.sharing_map()
        for w in self.later[k + 1:k + 3] + self.later[k + 3:][-1:]:  # the goal unless among the two
            q.reset(points=True)
            q.target(x, y, w, memory, True, now_us)
            if not q.no_route:
                return True
        return False


def traced(p: PlannedTarget) -> TracingTarget:
    """`p` (a `PlannedTarget` or a subclass) recording a `Trace` from now on."""
    p.__class__ = type("Traced" + type(p).__name__, (TracingTarget, type(p)), {})
    t = p if isinstance(p, TracingTarget) else None
    assert t is not None
    t.trace = Trace()
    t.later = []
    return t


def classify(outcome: str, tr: Trace, give_ways: int) -> str:
    """The decision that ended a failed episode (module docstring)."""
    if outcome == "no_route":
        last = tr.changes[-1] if tr.changes else (0, "", 0, 0, False)
        why = "declared:cap" if last[2] < 3 and last[3] >= 9 else "declared:still"
        return why + ("+gave_way" if give_ways else "")
    tail = tr.modes[-TAIL_PERIODS:]
    if outcome == "collision":
        return "collision:" + (tail[-1] if tail else "?")
    groups = Counter({"waiting": sum(m in (WAIT, "stand") for m in tail),
                      "giving_way": sum(m == GIVE_WAY for m in tail),
                      "backing_off": sum(m in (BACKUP, CLEAR) for m in tail),
                      "detour": sum(m == GLOBAL for m in tail),
                      "local": sum(m == LOCAL for m in tail)})
    return f"{outcome}:{groups.most_common(1)[0][0]}"


def standoff(gaps: list[float]) -> bool:
    """A stand-off at the end (module docstring): `gaps` the robot's body to the nearest mover's, per period."""
    tail = gaps[-STANDOFF_PERIODS:]
    return len(tail) == STANDOFF_PERIODS and sum(g < STANDOFF_GAP_MM for g in tail) >= 0.9 * STANDOFF_PERIODS


def trace(eps: list[Episode], maps: dict[str, GridMap], ctrl: NavController) -> list[dict]:
    """One row per episode: outcome, the decision that ended a failure (`classify`), the periods in
    each mode, the rounds of recoveries and give-ways, whether it ended in a stand-off, whether a later
    waypoint was reachable at its last "no route", whether it ended pinned between two movers (module
    docstring)."""
    from ground_station.lab.nav import planned
    from ground_station.lab.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, OUTCOMES, STALL_STEPS

    rows = []
    holder: list[TracingTarget] = []
    later: list[tuple[int, int]] = []

    def make(*args: Any) -> PlannedTarget:
        holder.append(traced(ctrl.planner(*args)))
        holder[-1].later = list(later)
        return holder[-1]

    gaps: list[float] = []
    seconds: list[float] = []  # to the second nearest mover: a sandwich is `standoff` on these

    def watch(x: float, y: float, movers: np.ndarray) -> None:
        near = sorted(math.hypot(mx - x, my - y) - r - robot_spec.ROBOT_RADIUS_MM
                      for mx, my, _, _, r, _ in movers.tolist()) + [math.inf, math.inf]
        gaps.append(near[0])
        seconds.append(near[1])

    for ep in eps:
        holder.clear()
        gaps.clear()
        seconds.clear()
        wps = rollout_arrays(ep, ctrl.guidance == "path")[2]  # the waypoints the rollout drives to
        later[:] = [(round(wx), round(wy)) for wx, wy in wps.tolist()]
        o, _, steps, _, _, _ = planned.rollout(ep, maps[ep.map], ctrl, BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS,
                                               make_planner=make, watch=watch)
        p = holder[0]
        tr = p.trace
        outcome = OUTCOMES[o]
        rows.append({"map": ep.map, "outcome": outcome, "success": outcome == "success",
                     "decision": None if outcome == "success" else classify(outcome, tr, p.give_ways),
                     "periods": steps, "modes": dict(Counter(tr.modes)), "rounds": p._all_rounds,
                     "give_ways": p.give_ways, "global_plans": p.global_plans, "standoff": standoff(gaps),
                     "sandwich": standoff(seconds),
                     "later_reachable": tr.later_open,
                     **({"blocked": {"detour": bool(ep.blocked["detour"])}} if ep.blocked else {})})
    return rows
