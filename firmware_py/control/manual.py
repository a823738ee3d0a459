"""Manual mode: the operator's sticks (MAVLink MANUAL_CONTROL) as wheel speeds,
with a deadman.

MANUAL_CONTROL's `x` (forward, -1000..1000) and `r` (yaw, clockwise positive)
become a differential command scaled to the robot's speed limit; a stick
not refreshed for DEADMAN_US on the control clock (sim time in HIL) stops the
wheels, so a lost link or a crashed joystick never leaves the robot driving.
The controller applies it only armed, in Manual, outside FAULT, and lets
safety win: e-stop, stale sensors and the failsafe end Manual driving through
their own paths; while the bumper is pressed only reversing is passed (the
operator can back off an obstacle, not push it). Pure: no clock, no I/O.
"""

from __future__ import annotations

import math

DEADMAN_US = 500_000
STICK_MAX = 1000
STICK_UNUSED = 0x7FFF  # MAVLink: INT16_MAX marks an axis the sender does not use


class ManualSticks:
    """The newest stick sample and when it arrived."""

    def __init__(self) -> None:
        self.x = 0
        self.r = 0
        self.t_us: int | None = None
        self.refused = 0  # samples out of range (not used)

    def update(self, x: int, r: int, now_us: int) -> bool:
        """Take a sample; False (and counted) if an axis is out of range."""
        x = 0 if x == STICK_UNUSED else x
        r = 0 if r == STICK_UNUSED else r
        if not (-STICK_MAX <= x <= STICK_MAX and -STICK_MAX <= r <= STICK_MAX):
            self.refused += 1
            return False
        self.x, self.r, self.t_us = int(x), int(r), now_us
        return True

    def fresh(self, now_us: int) -> bool:
        return self.t_us is not None and 0 <= now_us - self.t_us <= DEADMAN_US

    def clear(self) -> None:
        self.t_us = None

    def wheels(self, now_us: int, max_speed_mm_s: int, bumper: bool) -> tuple[int, int]:
        """Wheel speeds (mm/s) for this tick: zero when the deadman expired."""
        if not self.fresh(now_us):
            return 0, 0
        forward = self.x * max_speed_mm_s / STICK_MAX
        turn = self.r * max_speed_mm_s / STICK_MAX  # clockwise: the left wheel faster
        left, right = forward + turn, forward - turn
        scale = max(1.0, abs(left) / max_speed_mm_s, abs(right) / max_speed_mm_s)
        left, right = math.trunc(left / scale), math.trunc(right / scale)
        if bumper:
            left, right = min(left, 0), min(right, 0)
        return left, right
