"""Decision, one part of the controller: the active policy, its kind's driver (firmware_py.kinds) and
the kind's off-tick work, on the robot's own map. Its inputs and outputs: docs/architecture.md, "The
robot controller". It knows no kind: the registry builds the driver.
"""

from __future__ import annotations

from typing import Any

from firmware_py import kinds
from firmware_py.background import Background
from firmware_py.kinds import Decision, DriveTick, KindDriver
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.layout import Layout
from firmware_py.mapdata import OccupancyGrid
from firmware_py.policy import Policy


class KindPart:
    """The active policy and its kind at work (module docstring)."""

    def __init__(self, policy: Policy | None, *, lockstep: bool, layout: Layout = DEFAULT_LAYOUT) -> None:
        self.layout = layout  # the readings' geometry the kind gets (Layout.sector_layout)
        # the kind's off-tick work: stepped by the node between lockstep ticks (reproducible runs), a
        # worker thread otherwise (firmware_py.background)
        self.background = Background(threaded=not lockstep)
        # the robot's own map (qnav-robot --map FILE; mapdata.OccupancyGrid): a policy carrying another is
        # refused at boot and activation (policy.config_mismatch). None: the policy's map is taken as is
        self.robot_map: Any = None
        self.policy: Policy | None = None
        self.driver: KindDriver | None = None
        self.last_known_good: Policy | None = None
        self.localiser_margin_mm: int | None = None  # the policy's setting for the localiser (PolicyKind)
        self.target_mm: tuple[int, int] | None = None  # what the policy steered to (None: the goal itself)
        self.decided: tuple[int, int, tuple[int, ...]] = (-1, -1, ())  # state, action, Q row (telemetry)
        if policy is not None:
            self.install(policy, keep_last=False)

    def install(self, new: Policy | None, keep_last: bool = True) -> None:
        """Make `new` the active policy with a new driver of its kind (None: unload); the one it
        replaces becomes the last known good (`keep_last`)."""
        old = self.policy
        self.policy = new
        kind = kinds.of_policy(new) if new is not None else None
        self.driver = kind.driver(new, self.background, self.layout) if kind is not None and new is not None else None
        self.localiser_margin_mm = kind.localiser_margin_mm(new) if kind is not None and new is not None else None
        if keep_last and old is not None and new is not None:
            self.last_known_good = old

    def goal_index(self, x_mm: int, y_mm: int, policy: Policy | None = None) -> tuple[int, str]:
        """The policy table's index of a goal (a cell policy's target; -1 and a reason if none)."""
        pol = policy or self.policy
        return (0, "") if pol is None else kinds.of_policy(pol).goal_index(pol, x_mm, y_mm, self.layout.robot_radius_mm)

    def monitor_map(self) -> OccupancyGrid | None:
        """The map the collision monitor knows walls and corners by: the robot's, else the policy's."""
        return self.robot_map if self.robot_map is not None else (
            self.policy.map_grid if self.policy is not None else None)

    def map_mm(self) -> tuple[int, int] | None:
        """The robot's map extent in world mm (x east, y north, from 0): the active policy's
        recorded map geometry; None without one."""
        geo = self.policy.map_geometry if self.policy is not None else None
        if geo is None or geo.cell_mm <= 0 or geo.width <= 0 or geo.height <= 0:
            return None
        return geo.width * geo.cell_mm, geo.height * geo.cell_mm

    def step(self, tick: DriveTick) -> Decision:
        """The kind's decision for a DRIVING tick (kept for telemetry: the row read, the target)."""
        assert self.driver is not None
        d = self.driver.step(tick)
        if d.decided is not None:
            self.decided = d.decided
        self.target_mm = d.target_mm
        return d

    def interrupt(self) -> None:
        """The kind abandons any motion in progress (a stop, a new goal, a new pose)."""
        if self.driver is not None:
            self.driver.interrupt()

    def remembered(self) -> list[tuple[int, int]]:
        """Obstacle points the kind remembers (world mm), for the collision monitor."""
        return self.driver.remembered_obstacles() if self.driver is not None else []
