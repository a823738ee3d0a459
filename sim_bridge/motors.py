"""The motor driver model: two wheels, a watchdog and an e-stop latch.

Owns what the MotorDriver node does with `MotorCommand` and `EStop` frames and what it reports in
`MotorStatus`. Per wheel: first-order response to the setpoint, acceleration limit, speed limit.
Every command feeds a watchdog measured in SIM time (integer µs); when it expires the setpoints go
to zero and the status says so until the next command, as ODrive/VESC/DroneCAN ESCs do (zeroed at
once, a brake, not a ramp). Stall detection compares each wheel's speed with the ground speed the
world reports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from firmware_py import can_protocol as cp
from firmware_py import robot_spec


@dataclass(frozen=True)
class MotorParams:
    time_constant_s: float = 0.05
    accel_limit_mm_s2: float = 3000.0
    speed_limit_mm_s: int = robot_spec.MAX_WHEEL_SPEED_MM_S
    watchdog_ms: int = 200  # DroneCAN ESC_CMD_TIMO default
    stall_min_speed_mm_s: float = 50.0
    stall_ratio: float = 0.25  # ground speed below this fraction of wheel speed ...
    stall_time_ms: int = 300  # ... for this long is a stall


class MotorDriver:
    """Pure model: `command`/`estop` at a sim time, `step(dt)`, `status()` signals."""

    def __init__(self, params: MotorParams = MotorParams()) -> None:
        if params.watchdog_ms <= 0:
            raise ValueError(f"watchdog must be positive, got {params.watchdog_ms} ms")
        if not 0 < params.speed_limit_mm_s <= robot_spec.MAX_WHEEL_SPEED_MM_S:
            raise ValueError(f"speed limit must be in (0, {robot_spec.MAX_WHEEL_SPEED_MM_S}] mm/s, "
                             f"got {params.speed_limit_mm_s}")
        if params.time_constant_s <= 0 or params.accel_limit_mm_s2 <= 0:
            raise ValueError("motor time constant and acceleration limit must be positive")
        self.p = params
        self.target = [0.0, 0.0]  # mm/s setpoints after clamping
        self.speed = [0.0, 0.0]  # mm/s actual wheel speeds
        self.state = cp.MOTOR_IDLE
        self.watchdog_tripped = False
        self.estopped = False
        self.accel_limited = False
        self.errors = 0
        self.last_counter = 0
        self.last_command_us: int | None = None
        self.commands = 0
        self._stall_us = [0, 0]

    def command(self, left_mm_s: int, right_mm_s: int, counter: int, now_us: int) -> None:
        """A MotorCommand arrived at sim time `now_us`."""
        self.commands += 1
        self.last_counter = counter
        self.last_command_us = now_us
        if self.estopped:
            return
        limit = self.p.speed_limit_mm_s
        self.target = [float(max(-limit, min(limit, left_mm_s))),
                       float(max(-limit, min(limit, right_mm_s)))]
        self.watchdog_tripped = False
        self.state = cp.MOTOR_RUNNING

    def bad_command(self) -> None:
        self.errors |= cp.MOTOR_ERR_BAD_COMMAND

    def estop(self, engage: bool) -> None:
        if engage:
            self.estopped = True
            self.target = [0.0, 0.0]
            self.speed = [0.0, 0.0]
            self.state = cp.MOTOR_ESTOP
        elif self.estopped:
            self.estopped = False
            self.state = cp.MOTOR_IDLE  # wheels stay at zero until a fresh command

    def step(self, dt_us: int, now_us: int) -> tuple[float, float]:
        """Advance the wheels by `dt_us` ending at sim time `now_us`; returns mm/s."""
        if (self.state == cp.MOTOR_RUNNING and self.last_command_us is not None
                and now_us - self.last_command_us >= self.p.watchdog_ms * 1000):
            self.target = [0.0, 0.0]
            self.speed = [0.0, 0.0]  # brake: the wheels are zeroed, not ramped down
            self.watchdog_tripped = True
            self.state = cp.MOTOR_WATCHDOG_STOP
        dt = dt_us / 1e6
        alpha = 1.0 - math.exp(-dt / self.p.time_constant_s)
        max_dv = self.p.accel_limit_mm_s2 * dt
        limit = self.p.speed_limit_mm_s
        for i in (0, 1):
            dv = (self.target[i] - self.speed[i]) * alpha
            if abs(self.target[i] - self.speed[i]) <= max_dv:
                dv = self.target[i] - self.speed[i]  # settle exactly instead of creeping
            if dv > max_dv:
                dv, self.accel_limited = max_dv, True
            elif dv < -max_dv:
                dv, self.accel_limited = -max_dv, True
            self.speed[i] = max(-limit, min(limit, self.speed[i] + dv))
        return self.speed[0], self.speed[1]

    def observe_ground(self, ground_mm_s: tuple[float, float], dt_us: int) -> None:
        """Update the stall flags from the wheels' ground speeds."""
        bits = (cp.MOTOR_ERR_STALL_LEFT, cp.MOTOR_ERR_STALL_RIGHT)
        for i in (0, 1):
            wheel = abs(self.speed[i])
            stalled = (wheel >= self.p.stall_min_speed_mm_s
                       and abs(ground_mm_s[i]) < self.p.stall_ratio * wheel)
            self._stall_us[i] = self._stall_us[i] + dt_us if stalled else 0
            if self._stall_us[i] >= self.p.stall_time_ms * 1000:
                self.errors |= bits[i]
            else:
                self.errors &= ~bits[i]

    def status(self, counter: int = 0) -> dict[str, int]:
        """MotorStatus signals with the sample's rolling `counter` (taken modulo its width); resets
        the per-period accel-limited flag."""
        limit = self.p.speed_limit_mm_s
        signals = {
            "Mot_State": self.state,
            "Mot_WatchdogTripped": int(self.watchdog_tripped),
            "Mot_EStop": int(self.estopped),
            "Mot_AccelLimited": int(self.accel_limited),
            "Mot_Errors": self.errors,
            "Mot_CmdCounterLsb": self.last_counter & 0xFF,
            "Mot_LeftSpeed": max(-limit, min(limit, round(self.speed[0]))),
            "Mot_RightSpeed": max(-limit, min(limit, round(self.speed[1]))),
            "Mot_Counter": counter % cp.SENSOR_COUNTER_MODULUS,
        }
        self.accel_limited = False
        self.errors &= ~cp.MOTOR_ERR_BAD_COMMAND  # reported once
        return signals
