"""The wander that feeds global localisation: forward while the front is clear,
steering towards the side with more room (keeps the robot centred in a 500 mm
corridor), else turning in place. A pure rule on the range readings; the
controller decides when it runs and stops it.
"""

from __future__ import annotations

from firmware_py import robot_spec

EXPLORE_FORWARD_MM_S = 250
EXPLORE_TURN_MM_S = 160
EXPLORE_CLEAR_FRONT_MM = 450
EXPLORE_CLEAR_DIAGONAL_MM = 80  # a 500 mm corridor leaves ~200 mm; 80 mm on a diagonal is ~160 mm beside the path
EXPLORE_STEER_GAIN = 0.3  # (mm/s) / mm of left-right diagonal difference
EXPLORE_STEER_MM_S = 80
EXPLORE_TIMEOUT_US = 30_000_000


class Exploration:
    """When the wander runs: from `start` until the pose is localised, the robot may no longer
    move on its own (see `end_reason`), or EXPLORE_TIMEOUT_US has passed."""

    def __init__(self) -> None:
        self.until_us: int | None = None

    @property
    def running(self) -> bool:
        return self.until_us is not None

    def start(self, now_us: int) -> None:
        self.until_us = now_us + EXPLORE_TIMEOUT_US

    def stop(self) -> None:
        self.until_us = None

    def end_reason(self, *, localised: bool, may_move: bool, now_us: int) -> str:
        """Why the wander ends on this tick ("" if it goes on)."""
        if localised:
            return "localised"
        if not may_move:
            return "exploration stopped"
        if self.until_us is not None and now_us >= self.until_us:
            return "exploration timed out, not localised"
        return ""


def wander_wheels(ranges_mm: list[int] | tuple[int, ...], range_status: list[int] | tuple[int, ...]) -> tuple[int, int]:
    """Wheel speeds (mm/s) of one tick of the wander (the readings as the policy's eight sectors)."""

    def rng(k: int) -> int:
        st = range_status[k]
        return robot_spec.RANGE_MAX_MM if st == robot_spec.RANGE_TOO_FAR else (
            ranges_mm[k] if st == robot_spec.RANGE_VALID else 0)

    front = rng(0)
    left, right = rng(1), rng(7)
    if front > EXPLORE_CLEAR_FRONT_MM and min(left, right) > EXPLORE_CLEAR_DIAGONAL_MM:
        steer = max(-EXPLORE_STEER_MM_S, min(EXPLORE_STEER_MM_S, (left - right) * EXPLORE_STEER_GAIN))
        return round(EXPLORE_FORWARD_MM_S - steer), round(EXPLORE_FORWARD_MM_S + steer)
    return -EXPLORE_TURN_MM_S, EXPLORE_TURN_MM_S
