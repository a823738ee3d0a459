"""Progress watch: notice when the robot stops getting closer to its goal.

A sensor-based local policy can stall in front of an obstacle the map does
not show (it keeps turning, or waits for a mover) without any safety check
firing. `ProgressWatch.update(now_us, goal, dist_mm)` runs every DRIVING
tick; when the distance to the current goal has found no new minimum (by
`MIN_GAIN_MM`) for `timeout_us`, it returns a message once for that goal,
which the controller sends as a STATUSTEXT warning, so the operator (and
MAVProxy/QGC, beside the OBSTACLE_DISTANCE the robot streams) sees that
the way is blocked. A new goal re-arms it, and so does `restart()`, which
the controller calls whenever it starts driving to a goal: a mission
re-planned around the obstacle may begin with the very waypoint the robot
stalled at, and a second stall there must be reported again.
"""

from __future__ import annotations

NO_PROGRESS_US = 10_000_000  # 10 s of robot time without getting closer
MIN_GAIN_MM = 50  # closer by at least this counts as progress


class ProgressWatch:
    def __init__(self, timeout_us: int = NO_PROGRESS_US) -> None:
        self.timeout_us = timeout_us
        self._goal: tuple[int, int] | None = None
        self._best = 0
        self._since_us = 0
        self._reported = False

    def restart(self) -> None:
        """Forget the goal: the next `update` starts a new watch."""
        self._goal = None

    def update(self, now_us: int, goal: tuple[int, int], dist_mm: int) -> str | None:
        """The warning text, once per goal, when progress stalls; else None."""
        if goal != self._goal:
            self._goal, self._best, self._since_us, self._reported = goal, dist_mm, now_us, False
            return None
        if dist_mm < self._best - MIN_GAIN_MM:
            self._best, self._since_us = dist_mm, now_us
            self._reported = False
            return None
        if not self._reported and now_us - self._since_us >= self.timeout_us:
            self._reported = True
            secs = (now_us - self._since_us) // 1_000_000
            return f"no progress for {secs} s, {dist_mm} mm to go"
        return None
