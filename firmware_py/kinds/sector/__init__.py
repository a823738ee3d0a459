"""The `sector` kind: the paper's sector state (goal-bearing sector x binned ranges
of chosen sensors), one table decision every control period, its action a wheel
speed pair. Encoder section: u16 bearing_sectors, u8 n_sensors, u8 n_edges, the
sensor indices (u8), the range edges (u16 mm); then the action pairs (left,
right) mm/s.

With its map and `local_planner` metadata (`parse_metadata`: a `LocalPlannerConfig`,
kept as `policy.kind_config`) the policy steers round obstacles the map does not
show. The ground station plans waypoints on the known map; a box in a corridor or
a person walking past is not on it. What the robot does about them before the
learnt table steers is this package's, one module per concern: `encoder`,
`config` (the planner's parameters), `memory` (the obstacle memory), `planner`
(Dijkstra sub-goals), `recoveries` (the tick's side and the recoveries), `decide`
(the recovery decisions as a learnt table) and `guard` (the motion guard).

Which readings the map explains is generic map code (`firmware_py.mapdata`), as
the collision monitor asks it for every kind. A robot whose policy is of another
kind never imports this package (`firmware_py.kinds` imports a kind when a policy
of it is loaded).
"""

from __future__ import annotations

import struct
from typing import Any, cast

from firmware_py import robot_spec
from firmware_py.background import Background
from firmware_py.kinds.base import (
    PAIR,
    Decision,
    DriveTick,
    Goals,
    KindDriver,
    Policy,
    PolicyKind,
    Unpacked,
    wheel_actions,
)
from firmware_py.kinds.sector.config import META_KEY, LocalPlannerConfig
from firmware_py.kinds.sector.decide import META_KEY as RECOVERY_KEY
from firmware_py.kinds.sector.decide import recovery_table
from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.kinds.sector.guard import MotionGuard
from firmware_py.kinds.sector.memory import ObstacleMemory
from firmware_py.kinds.sector.recoveries import PlannedTarget
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.layout import Layout

KIND_NAME = "sector"
_HEAD = struct.Struct("<HBB")  # bearing_sectors, n_sensors, n_edges


def unpack(sec: bytes, n_actions: int, expect_sensors: int) -> Unpacked:
    if len(sec) < _HEAD.size:
        raise ValueError("sector encoder section too short")
    bearing, n_sensors, n_edges = _HEAD.unpack_from(sec, 0)
    need = _HEAD.size + n_sensors + 2 * n_edges + PAIR.size * n_actions
    if len(sec) != need:
        raise ValueError(f"sector encoder section is {len(sec)} bytes, its fields need {need}")
    if bearing < 1:
        raise ValueError("sector encoder: bearing_sectors is 0")
    if n_sensors < 1 or n_sensors > expect_sensors:
        raise ValueError(f"sector encoder uses {n_sensors} sensors, robot has {expect_sensors}")
    off = _HEAD.size
    sensors = tuple(sec[off:off + n_sensors])
    bad = [s for s in sensors if s >= expect_sensors]
    if bad:
        raise ValueError(f"sector encoder: sensor index {bad[0]} but robot has {expect_sensors} sensors")
    off += n_sensors
    edges = struct.unpack_from(f"<{n_edges}H", sec, off)
    off += 2 * n_edges
    if list(edges) != sorted(set(edges)) or (edges and edges[0] == 0):
        raise ValueError("sector encoder: range edges not strictly ascending positive mm")
    try:
        enc = SectorEncoder(bearing_sectors=bearing, sensors=sensors, range_edges_mm=edges)
    except ValueError as exc:
        raise ValueError(f"sector encoder: {exc}") from None
    return Unpacked(enc, (), 0, off)


def pack(enc: SectorEncoder, _goals: Goals, _cell_mm: int) -> bytes:
    return (_HEAD.pack(enc.bearing_sectors, len(enc.sensors), len(enc.range_edges_mm)) + bytes(enc.sensors)
            + struct.pack(f"<{len(enc.range_edges_mm)}H", *enc.range_edges_mm))


def parse_metadata(policy: Policy) -> LocalPlannerConfig | None:
    """The local planner's parameters from the policy's `local_planner` metadata (None: it has
    none, the table steers at the goal); ValueError with one line when they are bad or the file
    carries no map to plan on."""
    if META_KEY not in policy.metadata:
        if RECOVERY_KEY in policy.metadata:
            raise ValueError(f"{RECOVERY_KEY} needs the {META_KEY} metadata (its decisions are the planner's)")
        return None
    if policy.map_grid is None:
        raise ValueError(f"{META_KEY} needs a plain sector policy that carries its map")
    recovery_table(policy.metadata)  # checked at load: a bad table is refused with the file
    return LocalPlannerConfig.from_metadata(policy.metadata[META_KEY])


def planner_config(policy: Policy) -> LocalPlannerConfig | None:
    """A loaded policy's local planner parameters: a sector policy's `kind_config` (None for a
    policy of another kind, or one without `local_planner` metadata)."""
    cfg = policy.kind_config if policy.kind == KIND_NAME else None
    return cfg if isinstance(cfg, LocalPlannerConfig) else None


def localiser_margin_mm(policy: Policy) -> int | None:
    """With a local planner, readings the map does not explain at the tracked pose (unmapped
    obstacles, beyond the planner's margin) are withheld from the localiser: a few together start
    augmented MCL's random-particle recovery, which in a map of look-alike places jumps the
    estimate. control/estimate.PoseEstimate.statuses does the withholding."""
    cfg = planner_config(policy)
    return cfg.margin_mm if cfg is not None and policy.map_grid is not None else None


def header_fields(policy: Policy) -> dict[str, Any]:
    cfg = planner_config(policy)
    return {"local_planner": cfg.to_metadata() if cfg is not None else None}


class SectorDriver(KindDriver):
    """Encode (bearing, ranges) -> greedy action -> its wheel speeds; with a local planner the
    bearing is the sub-goal's and the motion guard may turn or back off the action."""

    def __init__(self, policy: Policy, work: Background | None = None, layout: Layout = DEFAULT_LAYOUT) -> None:
        super().__init__(policy, work, layout)
        cfg, grid = planner_config(policy), policy.map_grid
        self.local: tuple[PlannedTarget, ObstacleMemory, MotionGuard] | None = None
        if cfg is not None and grid is not None:
            cfg = cfg.for_body(layout.robot_radius_mm)  # the clearances round this robot's body
            self.local = (PlannedTarget(grid, cfg, self.work, layout.robot_radius_mm, recovery_table(policy.metadata)),
                          ObstacleMemory(cfg, layout),
                          MotionGuard(cfg, layout))
        self._key: tuple[tuple[int, int], int] | None = None

    def step(self, tick: DriveTick) -> Decision:
        pol = self.policy
        enc = cast(SectorEncoder, pol.encoder)
        bearing, target, speed = tick.goal_bearing_mrad, None, 100
        if self.local is not None:
            bearing, target, speed = self._local_bearing(tick)
        s = enc.encode(bearing, tick.ranges_mm, tick.range_status)
        a = pol.best_action(s)
        if self.local is not None:
            planner, memory, guard = self.local
            x, y, _ = tick.pose_mm
            a, speed = guard.step(tick.now_us, x, y, a, bearing, tick.ranges_mm, tick.range_status, memory,
                                  planner, speed, tick.blocked_us)
            if planner.no_route:
                return Decision((0, 0), self.decided(s, a), target, no_route=planner.no_route)
        left, right = robot_spec.ACTION_WHEEL_SPEEDS_MM_S[a]
        return Decision((left * speed // 100, right * speed // 100), self.decided(s, a), target)

    def _local_bearing(self, tick: DriveTick) -> tuple[int, tuple[int, int] | None, int]:
        """The bearing to the local planner's target for this tick, the target when it is not the
        goal itself (straight at the goal until an unmapped obstacle is in the way), and the speed in
        percent (reduced, then zero, while the planner's worker has no recent answer)."""
        assert self.local is not None and self.policy.map_grid is not None
        planner, memory, guard = self.local
        if tick.drive_key != self._key:  # a new goal (mission item, drive)
            planner.reset()
            if self._key is None or tick.drive_key[1] != self._key[1]:
                guard.reset()  # a new drive, not a new mission item (the twin: one guard per episode)
            self._key = tick.drive_key
        x, y, heading = tick.pose_mm
        memory.observe(self.policy.map_grid, x, y, heading, tick.ranges_mm, tick.range_status, tick.now_us)
        tx, ty, speed = planner.target(tick.now_us, x, y, tick.goal, memory)
        if not planner.detouring:
            return tick.goal_bearing_mrad, None, speed
        target = (round(tx), round(ty))
        return tick.goal_vector(*target)[1], target, speed

    def remembered_obstacles(self) -> list[tuple[int, int]]:
        if self.local is None:
            return []
        return [(x, y) for x, y, _ in self.local[1].points.values()]


def needs(enc: SectorEncoder, trained: Any) -> dict[str, Any]:
    """What a sector policy needs of the robot (firmware_py.needs): the sectors its encoder reads, to
    its top range edge, at the angles its twin read them; no larger a body than the twin's (its
    ranges are from that rim, its clearances learnt for it); a wheel base within 10 % of the twin's
    (its turn actions' rate)."""
    from firmware_py.needs import base_window, sector_needs

    return {"sectors": sector_needs(trained, tuple(enc.sensors), max(enc.range_edges_mm, default=0)),
            "robot_radius_mm_max": trained.robot_radius_mm, "wheel_base_mm": base_window(trained.wheel_base_mm)}


KIND = PolicyKind(name=KIND_NAME, code=2, actions=wheel_actions(), unpack=unpack, pack=pack, driver=SectorDriver,
                  header_fields=header_fields, parse_metadata=parse_metadata, localiser_margin_mm=localiser_margin_mm,
                  needs=needs)
