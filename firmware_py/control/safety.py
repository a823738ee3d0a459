"""Safety building blocks of the controller: the motor command watchdog,
the e-stop latch and wheel-speed clamping.

Pure logic on integer microseconds from the injected clock; the controller
(`firmware_py.control.controller`) holds a `SafetyChecks` (the input checks: freshness, frozen
senders, the motor driver's health, the e-stop latch) and decides the state transitions from its
verdicts.
"""

from __future__ import annotations

from dataclasses import dataclass

from firmware_py import robot_spec
from firmware_py.can_protocol import MOTOR_WATCHDOG_STOP
from firmware_py.control.io import Inputs
from firmware_py.control.plausibility import InputFreshness


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


@dataclass(frozen=True)
class Verdict:
    """What the safety checks found on one tick (see `SafetyChecks.check`)."""

    estop_tripped: bool  # the e-stop latched on this tick (armed)
    fault: str  # the first input fault while armed ("" none)
    stale: list[str]  # sensor inputs past the timeout
    driver_stale: str  # "", "stale" or "frozen"


class SafetyChecks:
    """The safety part: whether the inputs may be believed and the robot may move. Inputs: the
    input snapshot, the clock, the sensor timeout, and whether the robot is armed and since when it
    drives; out: a `Verdict`, or why it may not arm. The e-stop latch is its state."""

    def __init__(self, bumper: bool = True) -> None:
        self.bumper = bumper  # the robot has a bumper board (the profile's boards.bumper): its input must be fresh
        self.freshness = InputFreshness()  # rolling counters: frozen senders
        self.estop_latch = EStopLatch()

    def stale(self, inp: Inputs, now_us: int, timeout_us: int) -> list[str]:
        return self.freshness.stale(inp, now_us, timeout_us, self.bumper)

    def driver_stale(self, inp: Inputs, now_us: int, timeout_us: int) -> str:
        """"" while the motor driver's status is fresh, else why not: no status within the sensor
        timeout ("stale"), or frames whose rolling counter stopped advancing ("frozen": a stuck
        sender re-sending one frame)."""
        t = self.freshness.fresh_since(inp, "driver", inp.driver_us)
        if t is not None and now_us - t <= timeout_us:
            return ""
        return "stale" if t == inp.driver_us else "frozen"

    def arm_refusal(self, inp: Inputs, now_us: int, timeout_us: int) -> str:
        """Why the robot must not arm now ("" it may; the e-stop latch is cleared when it may)."""
        ok, why = self.estop_latch.may_arm(inp.estop or inp.driver_estop)
        if not ok:
            return why
        stale = self.stale(inp, now_us, timeout_us)
        if stale:
            return f"sensor data stale: {','.join(stale)}"
        if self.driver_stale(inp, now_us, timeout_us):
            return "motor driver silent"
        if inp.driver_errors:
            return inp.driver_detail or f"motor driver errors 0x{inp.driver_errors:02x}"
        return inp.arm_block

    def check(self, inp: Inputs, now_us: int, timeout_us: int, *, armed: bool,
              driving_since_us: int | None, grace_us: int) -> Verdict:
        """This tick's verdict. `driving_since_us`: when DRIVING began (None: not driving); the motor
        driver's own watchdog stop while driving, after `grace_us`, is a fault (commands lost)."""
        stale = self.stale(inp, now_us, timeout_us)
        driver_stale = self.driver_stale(inp, now_us, timeout_us)
        tripped, fault = False, ""
        if armed:
            tripped = (inp.estop or inp.driver_estop) and self.estop_latch.trip()
            detail = f": {inp.driver_detail}" if inp.driver_detail else ""
            if stale:
                fault = f"sensor data stale: {','.join(stale)}" + (detail if "encoders" in stale else "")
            elif driver_stale:
                fault = f"motor driver status {driver_stale}{detail}"
            elif inp.driver_errors:
                fault = inp.driver_detail or f"motor driver fault 0x{inp.driver_errors:02x}"
            elif (driving_since_us is not None and inp.driver_state == MOTOR_WATCHDOG_STOP
                  and inp.driver_us is not None and inp.driver_us - driving_since_us > grace_us):
                fault = "motor driver watchdog tripped while driving"
        return Verdict(tripped, fault, stale, driver_stale)
