"""The cell motion primitive, shared by the kinds that decide one cell move at a
time (`cell`, `sector-memory`): the kind names the next cell centre and the
grid heading to face; the stepper turns in place to that heading, drives to the
centre, and asks the kind again. Integer gains in mrad, mm and mm/s.
"""

from __future__ import annotations

from dataclasses import dataclass

from firmware_py import robot_spec
from firmware_py.control.odometry import wrap_mrad
from firmware_py.kinds.base import Decision, DriveTick, KindDriver
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT

TURN_TOLERANCE_MRAD = 35  # heading error at which a turn counts as done
ARRIVE_TOLERANCE_MM = 30  # distance to a cell centre at which a step is done
RETURN_TO_TURN_MRAD = 600  # bearing error that aborts a straight drive back to turning
TURN_GAIN_PER_S = 4  # wheel speed = gain * error * base/2, capped by the turn action
MIN_TURN_MM_S = 30
MIN_DRIVE_MM_S = 80
STEP_BLOCKED_US = 1_000_000  # a step the collision monitor held this long is offered to the kind (`blocked`)
DRIVE_GAIN_PER_S = 3  # forward speed = gain * distance, capped by the forward action
STEER_GAIN_PER_S = 3  # yaw rate (mrad/s) = gain * bearing (mrad)


@dataclass
class Step:
    """One cell step: turn to `heading_mrad`, then drive to `target`. `decided`: the table
    row read to choose it (telemetry)."""

    target: tuple[int, int]
    heading_mrad: int
    decided: tuple[int, int, tuple[int, ...]] | None = None
    turning: bool = True


class CellStepper(KindDriver):
    """A driver whose kind decides a cell step at a time (`next_step`); this class executes it."""

    def __init__(self, policy, work=None, layout=DEFAULT_LAYOUT) -> None:  # type: ignore[no-untyped-def]
        super().__init__(policy, work, layout)
        self.open: Step | None = None

    def next_step(self, tick: DriveTick) -> Step | str:
        """The next cell step from the current pose, or a fault's reason."""
        raise NotImplementedError

    def interrupt(self) -> None:
        self.open = None

    def blocked(self, tick: DriveTick, step: Step) -> Step | None:
        """The collision monitor has held `step` for STEP_BLOCKED_US: a step to take instead, or
        None to wait (a cell policy knows no other way to its cell)."""
        return None

    def step(self, tick: DriveTick) -> Decision:
        """Drive the open step; on arrival decide the next one and drive it (a second arrival in
        the same tick: stand still until the next)."""
        decided: tuple[int, int, tuple[int, ...]] | None = None
        if self.open is not None and not self.open.turning and tick.blocked_us >= STEP_BLOCKED_US:
            instead = self.blocked(tick, self.open)
            if instead is not None:
                self.open = instead
        for _ in (0, 1):
            if self.open is None:
                nxt = self.next_step(tick)
                if isinstance(nxt, str):
                    return Decision(None, fault=nxt)
                self.open = nxt
                decided = nxt.decided or decided
            wheels = self._execute(tick, self.open)
            if wheels is not None:
                return Decision(wheels, decided)
            self.open = None  # arrived (or just past it): re-localise from the pose
        return Decision((0, 0), decided)

    def _execute(self, tick: DriveTick, prim: Step) -> tuple[int, int] | None:
        """Wheel speeds for the open step; None once it has arrived."""
        _, _, heading = tick.pose_mm
        half_base = self.layout.wheel_base_mm // 2
        turn_cap = abs(robot_spec.ACTION_WHEEL_SPEEDS_MM_S[1][1])
        if prim.turning:
            err = wrap_mrad(prim.heading_mrad - heading)
            if abs(err) > TURN_TOLERANCE_MRAD:
                w = TURN_GAIN_PER_S * abs(err) * half_base // 1000
                w = max(MIN_TURN_MM_S, min(turn_cap, w))
                return (-w, w) if err > 0 else (w, -w)
            prim.turning = False
        dist, bearing = tick.goal_vector(*prim.target)
        # just past the centre counts as arrived within half a cell policy's cell (policy.cell_mm; 0 for
        # kinds without one)
        if dist <= ARRIVE_TOLERANCE_MM or (abs(bearing) > 1571 and dist < self.policy.cell_mm // 2):
            return None
        if abs(bearing) > RETURN_TO_TURN_MRAD:
            prim.turning = True
            prim.heading_mrad = wrap_mrad(heading + bearing)
            return (0, 0)
        fwd_cap = robot_spec.ACTION_WHEEL_SPEEDS_MM_S[0][0]
        v = max(MIN_DRIVE_MM_S, min(fwd_cap, DRIVE_GAIN_PER_S * dist))
        dv = STEER_GAIN_PER_S * bearing * half_base // 1000
        return (v - dv, v + dv)
