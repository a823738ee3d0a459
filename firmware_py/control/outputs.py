"""Outputs, one part of the controller: the wheel setpoint behind the motor watchdog, and the frames
one tick sends (the motor command with its counter, the heartbeat).

Its inputs: the setpoint whoever drives feeds it (`feed`; a policy kind, the wander, Manual), `stop`
on leaving motion, and per tick the command as the collision monitor let it through and what the
heartbeat reports (`frames`). It sends a command while the robot moves, in lockstep on every tick (the
handshake wants an answer), and after a stop `STOP_BURST_TICKS` zero commands, then nothing (the
driver's own watchdog holds the wheels, ODrive style).
"""

from __future__ import annotations

from firmware_py.control.io import Heartbeat, MotorCommand, Outputs
from firmware_py.control.safety import MotorWatchdog, clamp_speeds

STOP_BURST_TICKS = 3  # zero commands sent after leaving DRIVING when not in lockstep


class OutputStage:
    """The motor watchdog and the tick's frames (module docstring)."""

    def __init__(self, motor_timeout_us: int, lockstep: bool) -> None:
        self.watchdog = MotorWatchdog(motor_timeout_us)
        self.lockstep = lockstep
        self._stop_burst = 0
        self._cmd_counter = 0
        self._hb_counter = 0

    def feed(self, now_us: int, left: int, right: int) -> None:
        self.watchdog.feed(now_us, left, right)

    def stop(self) -> None:
        """Zero the setpoint now and send a few zero commands (when not in lockstep)."""
        self.watchdog.stop()
        self._stop_burst = STOP_BURST_TICKS

    def setpoint(self, now_us: int, limit_mm_s: int) -> tuple[int, int]:
        """The wheel speeds the watchdog lets through, clamped."""
        left, right = self.watchdog.output(now_us)
        return clamp_speeds(left, right, limit_mm_s)

    def frames(self, now_us: int, tick: int | None, left: int, right: int, *, moving: bool,
               state: int, mode: int, armed: bool, policy_loaded: bool, goal_active: bool, errors: int,
               drive_enabled: bool) -> Outputs:
        """The tick's frames: `tick` is the SimTick counter answered in lockstep (the command carries
        it); the rest is what the heartbeat reports."""
        if tick is not None:
            counter = tick & 0xFFFFFF
        else:
            self._cmd_counter = (self._cmd_counter + 1) & 0xFFFFFF
            counter = self._cmd_counter
        live = moving and not self.watchdog.expired(now_us)
        motor: MotorCommand | None
        if live or self.lockstep or tick is not None:
            motor = MotorCommand(left, right, counter)
        elif self._stop_burst > 0:
            self._stop_burst -= 1
            motor = MotorCommand(0, 0, counter)
        else:
            motor = None
        self._hb_counter = (self._hb_counter + 1) & 0xFF
        hb = Heartbeat(state=state, mode=mode, armed=armed, policy_loaded=policy_loaded, goal_active=goal_active,
                       errors=errors, counter=self._hb_counter)
        return Outputs(motor=motor, heartbeat=hb, drive_enabled=drive_enabled)
