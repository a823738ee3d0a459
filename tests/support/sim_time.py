"""Test-side moves of a `firmware_py.clock.SimClock`: a local, trusted step and a wait for sim time.
The robot only ever sets its SimClock from the sim's ticks (`SimClock.set_us`)."""

from __future__ import annotations

from firmware_py.clock import SimClock


def advance_us(clock: SimClock, dt_us: int) -> None:
    """Advance `clock` by `dt_us` (a local, trusted step: no jump check)."""
    with clock._changed:
        if dt_us > 0:
            clock._now += dt_us
            clock._changed.notify_all()


def wait_until(clock: SimClock, t_us: int, timeout_s: float | None = None) -> bool:
    """Block until sim time reaches `t_us` (wall `timeout_s` as a guard)."""
    with clock._changed:
        return clock._changed.wait_for(lambda: clock._now >= t_us, timeout_s)
