"""The contract every policy kind fulfils: `PolicyKind` (what the `.qtab` loader and
writer need: the kind's name and file code, its action set, its encoder section)
and `KindDriver` (what the controller calls each tick while DRIVING).

The controller keeps the states, modes and safety and knows no kind: it asks the
registry (`firmware_py.kinds`) for the policy's kind, builds that kind's driver
when the policy is activated, and each tick hands it a `DriveTick` and takes back
a `Decision` (wheel speeds, or a fault). A kind's memory (a Bug wall memory, a
local planner's obstacle memory, an open cell step) lives in its driver.

No import of `firmware_py.policy` (it imports the registry): kinds see a loaded policy through
`Policy` below, and raise `ValueError` with a one-line reason, which the loader turns into a
`PolicyError`.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from firmware_py import robot_spec
from firmware_py.background import Background
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.layout import Layout

PAIR = struct.Struct("<hh")  # one action in the encoder section: (left, right) mm/s or (dcol, drow)
Geometry = tuple[int, int, int]  # (cell_mm, width, height) of a map
Goals = tuple[tuple[int, int], ...]


class Encoder(Protocol):
    """What the loader needs of any kind's encoder."""

    @property
    def kind(self) -> str: ...

    @property
    def n_states(self) -> int: ...

    @property
    def n_actions(self) -> int: ...

    def to_dict(self) -> dict[str, object]: ...


class Policy(Protocol):
    """What a kind uses of a loaded policy (firmware_py.policy.Policy has it all)."""

    @property
    def kind(self) -> str: ...

    @property
    def encoder(self) -> Any: ...

    @property
    def goals(self) -> Goals: ...

    @property
    def cell_mm(self) -> int: ...

    @property
    def map_grid(self) -> Any: ...

    @property
    def metadata(self) -> dict[str, Any]: ...

    @property
    def kind_config(self) -> Any: ...

    def row(self, state: int) -> Any: ...

    def best_action(self, state: int) -> int: ...


@dataclass(frozen=True)
class Unpacked:
    """A kind's encoder section, read: the encoder, a cell policy's goal cells and cell size, and
    where the action pairs start."""

    encoder: Any
    goals: Goals = ()
    cell_mm: int = 0
    actions_at: int = 0


@dataclass(frozen=True)
class DriveTick:
    """What a kind sees on a tick while DRIVING (all on the controller's clock)."""

    now_us: int
    goal: tuple[int, int]
    goal_index: int
    # (goal, time DRIVING began): a new value is a new goal (a mission item) or a new drive
    drive_key: tuple[tuple[int, int], int]
    pose_mm: tuple[int, int, int]  # the pose the robot drives by (localiser, else odometry)
    goal_bearing_mrad: int
    ranges_mm: tuple[int, ...] | list[int]
    range_status: tuple[int, ...] | list[int]
    goal_vector: Callable[[int, int], tuple[int, int]]  # (distance, bearing) from the pose to a point
    # how long the collision monitor (control/collision.py), downstream of the kind's command, has
    # kept the straight part of it at zero, up to the last tick (0: it does not): a kind may give the
    # move up and choose another. The one thing the kind learns of what happened to its command
    blocked_us: int = 0


@dataclass(frozen=True)
class Decision:
    """A kind's answer for one tick. `wheels` None: no command this tick (see `fault`).
    `decided` (state, action, Q row) when a table row was read this tick, for telemetry;
    None keeps the last one (a cell step decides once per cell)."""

    wheels: tuple[int, int] | None
    decided: tuple[int, int, tuple[int, ...]] | None = None
    target_mm: tuple[int, int] | None = None  # what the kind steered to when not the goal itself
    fault: str = ""
    # the goal cannot be reached (a planner's recoveries ran out): the controller reports it and ends the
    # mission in HOLD; `wheels` is then (0, 0)
    no_route: str = ""


class KindDriver:
    """A policy kind at work on the robot: one per active policy, built by `PolicyKind.driver`."""

    def __init__(self, policy: Policy, work: Background | None = None, layout: Layout = DEFAULT_LAYOUT) -> None:
        self.policy = policy
        # the geometry of the readings a DriveTick carries (the policy's sectors, each at the angle of
        # the robot's sensor behind it; the body, the wheels: firmware_py.layout.Layout.sector_layout)
        self.layout = layout
        # where the kind runs work that must not run in the tick (firmware_py.background): the
        # controller's, stepped between ticks in lockstep HIL; a worker thread of its own otherwise
        self.work = work if work is not None else Background()

    def step(self, tick: DriveTick) -> Decision:
        """The wheel command for this tick (mm/s, before the speed scale and clamp)."""
        raise NotImplementedError

    def interrupt(self) -> None:
        """Abandon any motion in progress: the robot stopped, was given a new goal or a new pose."""

    def remembered_obstacles(self) -> list[tuple[int, int]]:
        """World points (mm) of obstacles the kind remembers seeing (default none): the collision
        monitor counts them too, covering the gaps between the range sensors' cones."""
        return []

    def decided(self, state: int, action: int) -> tuple[int, int, tuple[int, ...]]:
        return state, action, tuple(self.policy.row(state))


def _none(*_args: Any) -> None:
    """A `PolicyKind` hook's default: none (no fixed geometry, cell size, config or margin)."""
    return None


def _empty(*_args: Any) -> dict[str, Any]:
    """A `PolicyKind` hook's default: no header fields, no needs."""
    return {}


def free_goal(policy: Policy, x_mm: int, y_mm: int, radius_mm: int = robot_spec.ROBOT_RADIUS_MM) -> tuple[int, str]:
    """Any goal the robot fits at, on the policy's map when it carries one:
    not outside it, in a wall, or closer to either than the robot's radius
    (`radius_mm`, the profile's body: firmware_py.layout)."""
    grid = policy.map_grid
    if grid is None:
        return 0, ""
    if not (0 <= x_mm < grid.width * grid.cell_mm and 0 <= y_mm < grid.height * grid.cell_mm):
        return -1, f"goal ({x_mm}, {y_mm}) mm is outside the map"
    if grid.occupied(*robot_spec.world_to_cell(x_mm, y_mm, grid.height, grid.cell_mm)):
        return -1, f"goal ({x_mm}, {y_mm}) mm is inside a wall"
    clear = grid.clearance_mm(x_mm, y_mm, radius_mm)
    if clear < radius_mm:
        return -1, f"goal ({x_mm}, {y_mm}) mm is {clear:.0f} mm from a wall (robot radius {radius_mm})"
    return 0, ""


@dataclass(frozen=True)
class PolicyKind:
    """One kind of `.qtab` policy, as the registry knows it (docs/policy-format.md).

    `unpack(section, n_actions, expect_sensors)` reads the encoder section up to its action pairs
    (every length checked; ValueError with the reason); `pack(encoder, goals, cell_mm)` writes it;
    the action pairs after them are the kind's `actions`, checked and written by the format.
    """

    name: str
    code: int
    actions: tuple[tuple[int, int], ...]
    unpack: Callable[[bytes, int, int], Unpacked]
    pack: Callable[[Any, Goals, int], bytes]
    driver: Callable[[Policy, Background, Layout], KindDriver]
    # the map geometry the header must record (a cell policy's own grid), or None: the training map's
    fixed_geometry: Callable[[Any, int], Geometry | None] = field(default=_none)
    # the map cell size the policy drives on, which must be the robot's (None: not cell-bound)
    robot_cell_mm: Callable[[Policy], int | None] = field(default=_none)
    # a goal's index for the table, or -1 and why it cannot be a goal of this policy; the last argument
    # is the robot's body radius (firmware_py.layout)
    goal_index: Callable[[Policy, int, int, int], tuple[int, str]] = field(default=free_goal)
    header_fields: Callable[[Policy], dict[str, Any]] = field(default=_empty)
    # what the kind reads from the file's metadata (the loader keeps it as `policy.kind_config`; the
    # sector kind's local planner parameters), from the loaded policy; ValueError with the reason
    parse_metadata: Callable[[Policy], Any] = field(default=_none)
    # the table is indexed by one map's cells (a cell policy): it runs only on the map it was trained
    # on. Other kinds observe ranges and bearings and take the robot's own map
    map_specific: bool = False
    # readings the policy's map does not explain at the tracked pose (beyond this margin, mm) are
    # withheld from the localiser while the policy drives (None: it weighs them all). A setting of the
    # policy, read once when it is activated: the kind sends the localiser nothing at run time
    localiser_margin_mm: Callable[[Policy], int | None] = field(default=_none)
    # what a policy of this kind needs of the robot beyond the control period and the wheel speed
    # (firmware_py.needs: the sectors it reads, the body and wheel base its twin assumed), from its
    # encoder and the robot it was trained for (a firmware_py.needs.TrainedFor); {}: nothing more
    needs: Callable[[Any, Any], dict[str, Any]] = field(default=_empty)

    def __post_init__(self) -> None:
        if not 1 <= self.code <= 255:
            raise ValueError(f"kind code {self.code} outside 1..255")
        if not self.name or not self.actions:
            raise ValueError("a kind needs a name and an action set")


def wheel_actions() -> tuple[tuple[int, int], ...]:
    """The action set of kinds that command wheel speeds directly (robot_spec)."""
    return tuple((left, right) for left, right in robot_spec.ACTION_WHEEL_SPEEDS_MM_S)


def best_action(row: list[int] | tuple[int, ...] | memoryview) -> int:
    """Greedy action of one Q-table row; ties break to the lowest index."""
    return max(range(len(row)), key=row.__getitem__)
