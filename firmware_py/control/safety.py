"""Safety building blocks of the controller: the motor command watchdog,
the e-stop latch and wheel-speed clamping.

Pure logic on integer microseconds from the injected clock; the controller
(`firmware_py.control.controller`) composes them and decides the state transitions.
"""

from __future__ import annotations

from firmware_py import robot_spec


def clamp_speeds(left_mm_s: int, right_mm_s: int, limit_mm_s: int) -> tuple[int, int]:
    """Clamp both wheel speeds to +-min(limit, the robot's hard limit)."""
    lim = max(0, min(int(limit_mm_s), robot_spec.MAX_WHEEL_SPEED_MM_S))
    return (max(-lim, min(lim, int(left_mm_s))), max(-lim, min(lim, int(right_mm_s))))


class MotorWatchdog:
    """The controller's side of the motor-driver watchdog (ODrive style).

    A setpoint only reaches the wheels while the watchdog is fed; the
    controller feeds it only while DRIVING. Unfed for `timeout_us`, or after
    `stop()`, the output is (0, 0), so a stalled decision path can never
    leave the last speed running.
    """

    def __init__(self, timeout_us: int) -> None:
        self.timeout_us = timeout_us
        self._fed_us: int | None = None
        self._setpoint = (0, 0)
        self.expirations = 0
        self._expired_reported = True

    def feed(self, now_us: int, left_mm_s: int, right_mm_s: int) -> None:
        self._fed_us = now_us
        self._setpoint = (left_mm_s, right_mm_s)
        self._expired_reported = False

    def stop(self) -> None:
        """Zero the output immediately (every transition out of DRIVING)."""
        self._fed_us = None
        self._setpoint = (0, 0)
        self._expired_reported = True

    def expired(self, now_us: int) -> bool:
        return self._fed_us is None or now_us - self._fed_us > self.timeout_us

    def output(self, now_us: int) -> tuple[int, int]:
        """The setpoint to send now: the fed one, or zero once expired."""
        if self.expired(now_us):
            if not self._expired_reported:
                self.expirations += 1
                self._expired_reported = True
            self._setpoint = (0, 0)
            self._fed_us = None
            return (0, 0)
        return self._setpoint


class EStopLatch:
    """An emergency stop stays latched until the vehicle is disarmed and then
    re-armed with the e-stop input released."""

    def __init__(self) -> None:
        self.latched = False
        self._disarmed_since_trip = False

    def trip(self) -> bool:
        """Latch (returns True when this is a new latch)."""
        new = not self.latched
        self.latched = True
        self._disarmed_since_trip = False
        return new

    def on_disarm(self) -> None:
        if self.latched:
            self._disarmed_since_trip = True

    def may_arm(self, estop_input_active: bool) -> tuple[bool, str]:
        """Whether an arm request may clear the latch; clears it if so."""
        if estop_input_active:
            return False, "e-stop is active"
        if self.latched and not self._disarmed_since_trip:
            return False, "e-stop latched: disarm first"
        self.latched = False
        self._disarmed_since_trip = False
        return True, ""
