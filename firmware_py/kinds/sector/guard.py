"""The sector kind's motion guard (`MotionGuard`): the last word on the learnt
table's action (as nav2's collision monitor and back-up recovery have for its
controllers), one per drive.

A forward step is replaced by a turn toward the target while the front or
a front diagonal sensor reads nearer than `veto_mm` (a round robot
turning in place touches nothing), and a robot that has not moved
`stuck_mm` for `stuck_us` with a remembered point within its radius +
`backoff_near_mm` backs off for `backoff_us` if the rear sensors are
clear (checked every tick of it, which also ends when a side reading
falls to `veto_mm` or under: something closing in beside the robot): a
person pinned between a wall and the robot can then step aside. A
forward step the collision monitor has held `HELD_TURN_US` is turned
toward the target, as a veto.

A turn in place toward a target behind the robot (more than
`TURN_COMMIT_MRAD` off the heading) is kept the way it began: the
table's bearing sectors meet behind the robot, and one turn step there
flips the target to the other side (left, right, left for good).
Nearer ahead, after `DITHER_REVERSALS` reversals in a row the guard
steps forward when the front sensors read at least twice `veto_mm`.

A body the map does not explain (the obstacle memory holds it that
near) touching the flank or a front diagonal ahead of the axle (a mover
that walked up to the robot and stands while it would overlap it) is
turned away from, the same way whatever the table asks, until a step
ahead is clear by `collision.travel_gap_mm`, then `ESCAPE_STEPS` steps
are taken ahead (`MotionGuard._escape`): the table, or the front veto
turning toward a target on the body's side, would turn into it and back
on the spot while the collision monitor held every step. A reverse the
monitor holds `HELD_TURN_US` is turned toward the target as a held
forward step is.
"""

from __future__ import annotations

import math

from firmware_py import robot_spec
from firmware_py.control import collision
from firmware_py.kinds.sector.config import LocalPlannerConfig
from firmware_py.kinds.sector.memory import ObstacleMemory
from firmware_py.kinds.sector.recoveries import PlannedTarget
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.layout import Layout

FORWARD, TURN_LEFT, TURN_RIGHT, REVERSE = range(4)  # robot_spec.ACTION_NAMES order
TURN_COMMIT_MRAD = 1571  # a turn toward a target further round than this keeps its direction (MotionGuard)
DITHER_REVERSALS = 3  # turn reversals in a row after which the guard steps forward if the front is open
ESCAPE_STEPS = 5  # steps ahead (100 mm) after turning away from a body at the flank (MotionGuard._escape)
ESCAPE_US = 3_000_000  # at most this long turning away from it
HELD_TURN_US = 500_000  # a forward step the collision monitor holds this long is turned (MotionGuard)
_FRONT = (robot_spec.SENSOR_COUNT - 1, 0, 1)  # -45, 0, +45 deg
_REAR, _REAR_SIDES, _SIDES = 4, (3, 5), (2, 6)
_LEFT_HALF, _RIGHT_HALF = (1, 2), (6, 7)  # the diagonals and sides ahead of the axle


class MotionGuard:
    """The last word on the learnt table's action (see the module docstring); one per drive."""

    def __init__(self, cfg: LocalPlannerConfig, layout: Layout = DEFAULT_LAYOUT) -> None:
        # the sector readings' geometry (firmware_py.layout): the body's radius, the collision fan
        self.radius_mm = layout.robot_radius_mm
        self._fan = collision.DEFAULT_FAN if layout == DEFAULT_LAYOUT else collision.Fan(layout)
        self.cfg = cfg
        self.vetoes = 0  # forward steps replaced by a turn (telemetry / benchmarks)
        self.reset()

    def reset(self) -> None:
        self._anchor: tuple[float, float] | None = None
        self._anchor_us = 0
        self._backing_until_us = -1
        self._last = FORWARD  # the action taken on the last tick
        self._reversals = 0  # ticks in a row the turn reversed
        self._side_ref: list[float] | None = None  # the side readings when the current back-off began
        self._escape_turn: int | None = None  # turning away from a body at the flank (_escape)
        self._escape_until_us = 0
        self._escape_steps = 0  # steps ahead still to take after the escape turn

    def action(self, now_us: int, x: float, y: float, action: int, bearing_mrad: int,
               ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
               memory: ObstacleMemory, detouring: bool = False, held_us: int = 0) -> int:
        """The action to take (`detouring`: the planner steers to a sub-goal, not the waypoint: a
        robot stuck on its way there backs off wherever it stands). `held_us`: how long the
        collision monitor (control/collision.py) has held the straight part: a forward step it holds
        HELD_TURN_US is turned toward the target instead, as a veto."""
        action = self._act(now_us, x, y, action, bearing_mrad, ranges_mm, status, memory, detouring, held_us)
        self._note_reverse(action == REVERSE, ranges_mm, status)
        return action

    def _act(self, now_us: int, x: float, y: float, action: int, bearing_mrad: int,
             ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
             memory: ObstacleMemory, detouring: bool, held_us: int) -> int:
        """`action` without keeping the back-off's side readings (`step` keeps them for its own)."""
        action = self._decide(now_us, x, y, action, bearing_mrad, ranges_mm, status, memory, detouring, held_us)
        turns = (TURN_LEFT, TURN_RIGHT)
        if action in turns and self._last in turns and action != self._last:
            self._reversals += 1
            if abs(bearing_mrad) > TURN_COMMIT_MRAD:
                action = self._last  # the target is behind: finish the turn begun (module docstring)
            elif self._reversals >= DITHER_REVERSALS and all(
                    collision.reading_mm(ranges_mm, status, i) >= 2 * self.cfg.veto_mm for i in _FRONT):
                # left, right, left on the spot: a step ahead breaks it (or, a body at the flank in
                # the way of that step, turning away from it)
                action, self._reversals = self._escape(now_us, x, y, FORWARD, ranges_mm, status, memory), 0
        elif action != self._last:
            self._reversals = 0
        self._last = action
        return action

    def _note_reverse(self, backing: bool, ranges_mm: list[int] | tuple[int, ...],
                      status: list[int] | tuple[int, ...]) -> None:
        """Keep the side readings of a back-off's first tick (`may_reverse` compares with them) while
        a back-off goes on or is asked for (a recovery's, refused, stays refused to its end)."""
        if not backing:
            self._side_ref = None
        elif self._side_ref is None:
            self._side_ref = [collision.reading_mm(ranges_mm, status, i) for i in _SIDES]

    def _decide(self, now_us: int, x: float, y: float, action: int, bearing_mrad: int,
                ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
                memory: ObstacleMemory, detouring: bool, held_us: int = 0) -> int:
        cfg = self.cfg
        if self._anchor is None or math.hypot(x - self._anchor[0], y - self._anchor[1]) > cfg.stuck_mm:
            self._anchor, self._anchor_us = (x, y), now_us
        if now_us < self._backing_until_us:
            if self.may_reverse(ranges_mm, status):
                return REVERSE
            self._backing_until_us = -1  # something came up behind: no more backing (checked every tick)
        if (now_us - self._anchor_us >= cfg.stuck_us and self.may_reverse(ranges_mm, status)
                and (detouring or memory.within(x, y, self.radius_mm + cfg.backoff_near_mm))):
            self._backing_until_us = now_us + cfg.backoff_us
            self._anchor, self._anchor_us = (x, y), now_us + cfg.backoff_us
            return REVERSE
        toward = TURN_LEFT if bearing_mrad >= 0 else TURN_RIGHT
        if action in (FORWARD, REVERSE) and held_us >= HELD_TURN_US:
            # (the table's own reverse too: held against a mover at the rear flank, it was asked for
            # as long as nothing changed, and nothing did)
            self.vetoes += 1
            return toward
        action = self._escape(now_us, x, y, action, ranges_mm, status, memory)
        if action == FORWARD and any(collision.reading_mm(ranges_mm, status, i) < cfg.veto_mm for i in _FRONT):
            self.vetoes += 1
            self._escape_steps = 0
            return toward
        return action

    def _escape(self, now_us: int, x: float, y: float, action: int, ranges_mm: list[int] | tuple[int, ...],
                status: list[int] | tuple[int, ...], memory: ObstacleMemory) -> int:
        """Away from a body touching the flank or a front diagonal ahead of the axle (module
        docstring): a step ahead rubs into it, and a turn back toward the target undoes a single turn
        away. So: turn away, the same way, until a step ahead is clear (collision.travel_gap_mm), then
        ESCAPE_STEPS steps ahead; at most ESCAPE_US of turning at a time. Only for a body the obstacle
        memory holds that near: a map corner beside the robot is the collision monitor's."""
        flank = [robot_spec.RANGE_TOO_FAR if i == 0 else st for i, st in enumerate(status)]  # ahead: the veto's
        # (no flank reading under CONTACT_MM: nothing there comes within veto_mm of a step ahead, and
        # the tick is spared the geometry)
        blocked = (collision.touching(ranges_mm, flank, self._fan)
                   and collision.travel_gap_mm(ranges_mm, flank, False, fan=self._fan) < self.cfg.veto_mm
                   and memory.within(x, y, self.radius_mm + collision.CONTACT_MM))
        if self._escape_turn is not None:
            if blocked and now_us < self._escape_until_us:
                self.vetoes += 1
                return self._escape_turn
            self._escape_turn, self._escape_steps = None, 0 if blocked else ESCAPE_STEPS
        if self._escape_steps > 0:
            self._escape_steps -= 1
            if not blocked:
                return FORWARD
            self._escape_steps = 0
        if action == FORWARD and blocked:
            self.vetoes += 1
            left = min(collision.reading_mm(ranges_mm, status, i) for i in _LEFT_HALF)
            right = min(collision.reading_mm(ranges_mm, status, i) for i in _RIGHT_HALF)
            self._escape_turn = TURN_RIGHT if left < right else TURN_LEFT
            self._escape_until_us = now_us + ESCAPE_US
            return self._escape_turn
        return action

    def step(self, now_us: int, x: float, y: float, action: int, bearing_mrad: int,
             ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...],
             memory: ObstacleMemory, planner: PlannedTarget, speed: int, held_us: int = 0) -> tuple[int, int]:
        """(action, speed %) after the guard and the planner's recoveries, as the robot's sector kind
        and the twin's bench both take them: a planned stand-still is not 'stuck', and a recovery's
        back-off reverses at full speed while the rear is clear. `held_us`: as `action`."""
        if speed == 0:
            self.still(now_us)
        action = self._act(now_us, x, y, action, bearing_mrad, ranges_mm, status, memory, planner.detouring,
                           held_us)
        if planner.reverse and self.may_reverse(ranges_mm, status):
            action, speed = REVERSE, 100
        self._note_reverse(action == REVERSE or planner.reverse, ranges_mm, status)
        return action, speed

    def still(self, now_us: int) -> None:
        """The planner holds the robot still on purpose (a recovery's wait): not stuck."""
        if self._anchor is not None:
            self._anchor_us = now_us

    def rear_clear(self, ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...]) -> bool:
        cfg = self.cfg
        return (collision.reading_mm(ranges_mm, status, _REAR) > cfg.rear_clear_mm
                and all(collision.reading_mm(ranges_mm, status, i) > cfg.rear_side_clear_mm for i in _REAR_SIDES))

    def may_reverse(self, ranges_mm: list[int] | tuple[int, ...], status: list[int] | tuple[int, ...]) -> bool:
        """The rear is clear, and no side reading has fallen to veto_mm or under since the back-off
        began (a small disc between the side and rear-diagonal cones comes into the side sensor's view
        only as the robot backs onto it). A wall alongside, read as near all the way, does not stop it."""
        if not self.rear_clear(ranges_mm, status):
            return False
        ref = self._side_ref
        if ref is None:
            return True
        now = [collision.reading_mm(ranges_mm, status, i) for i in _SIDES]
        return all(d > self.cfg.veto_mm or d >= r for d, r in zip(now, ref, strict=True))
