"""Progress watch: notice when the robot stops getting closer to its goal.

A sensor-based local policy can stall in front of an obstacle the map does
not show without any safety check firing. `ProgressWatch.update` runs every
DRIVING tick; when the distance to the current goal has found no new minimum
(by `MIN_GAIN_MM`) for `timeout_us`, it returns a message once for that goal,
which the controller sends as a STATUSTEXT warning. A new goal re-arms it, and
so does `restart()`, called whenever a drive to a goal starts: a re-planned
mission may begin with the very waypoint the robot stalled at, and a second
stall there must be reported again.

`StallWatch` (below) is the action beside this warning: a drive that neither
gets closer nor moves for NAV_STALL_S is reported with its reason and held.
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


# --- the stall watch (NAV_STALL_S) ----------------------------------------------------------------

STALL_MOVE_MM = 250  # moving this far from where the window began counts as progress (nav2's radius)


class StallWatch:
    """Notice a robot commanded to drive that gets nowhere, and say why.

    Where `ProgressWatch` only warns, this is the action, as nav2's progress checker aborts a goal
    and ArduPilot holds: `update` returns
    a reason once the robot has neither got `MIN_GAIN_MM` closer to its goal than ever on this
    drive nor moved `STALL_MOVE_MM` from where the window began for `timeout_us` (a detour away
    from the goal is progress while the robot moves), and the controller reports it and holds.

    `note` counts, per DRIVING tick, what the robot knows of why: the command it sent, whether the
    collision monitor removed the straight part (or nothing was sent with a reading in the way
    ahead) and whether the encoders turned. The reason is "wheels not moving" when the wheels were
    commanded most of the window but the encoders hardly turned, "blocked ahead" when the way
    ahead was shut most of it, else "no progress". A new `key` (the goal and when the drive began)
    starts a new watch; a goal sent again while driving to it does not. `timeout_us` <= 0: off.
    """

    def __init__(self) -> None:
        self._key: object = None
        self._best = 0
        self._at = (0, 0)
        self._since_us = 0
        self._enc: tuple[int, int] | None = None
        self._ticks = self._blocked = self._commanded = self._turned = 0
        self.count = 0  # stalls reported since boot (robot_stats.json `stalls`)

    def _window(self, now_us: int, x_mm: int, y_mm: int) -> None:
        self._at, self._since_us = (x_mm, y_mm), now_us
        self._ticks = self._blocked = self._commanded = self._turned = 0

    def note(self, commanded: bool, blocked: bool, encoders: tuple[int, int] | None) -> None:
        """One DRIVING tick: a non-zero command sent, the way ahead shut, the encoder counts."""
        self._ticks += 1
        self._blocked += blocked
        self._commanded += commanded
        self._turned += commanded and encoders is not None and self._enc is not None and encoders != self._enc
        self._enc = encoders

    def reason(self) -> str:
        if self._commanded * 2 > self._ticks and self._turned * 10 < self._commanded:
            return "wheels not moving"
        return "blocked ahead" if self._blocked * 2 > self._ticks else "no progress"

    def update(self, now_us: int, key: object, dist_mm: int, x_mm: int, y_mm: int, timeout_us: int) -> str | None:
        """The reason, when the drive has stalled for `timeout_us`; else None."""
        if key != self._key:
            self._key, self._best = key, dist_mm
            self._window(now_us, x_mm, y_mm)
            return None
        closer = dist_mm < self._best - MIN_GAIN_MM
        if closer:
            self._best = dist_mm
        if closer or (x_mm - self._at[0]) ** 2 + (y_mm - self._at[1]) ** 2 >= STALL_MOVE_MM ** 2:
            self._window(now_us, x_mm, y_mm)
            return None
        if timeout_us <= 0 or now_us - self._since_us < timeout_us:
            return None
        why = self.reason()
        self.count += 1
        self._window(now_us, x_mm, y_mm)
        return why
