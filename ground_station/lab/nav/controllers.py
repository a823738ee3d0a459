"""The controllers `qnav bench nav` compares, all through one interface.

A `NavController` is a table over a reference `SectorEncoder` state
(goal-bearing sector x binned ranges) plus the guidance it drives with:
"path" (the planner's waypoints as a mission) or "direct" (the goal alone).
That is exactly what the robot runs (`Controller.step`: encoder -> greedy
row -> action), so every controller also runs in HIL as an exported
`.qtab` (`NavController.policy()`), and the twin rolls the same table out.

* `learnt`: the trained sector policy (a `.qtab`), guidance path;
* `seek`: the hand-written seek table (`learn.sector.evaluate.seek_table`:
  forward when the target is in the sector ahead, else turn to it), path;
* `vfh`: a Vector-Field-Histogram-style reactive controller on the same
  range sectors (`vfh_table`), path;
* `direct`: the paper's direct setting, the learnt table steering on the
  goal's bearing alone (no waypoints);
* `seek_local` (only with a learnt policy that carries local-planner
  parameters): the seek table steering on the same local planner's targets,
  i.e. what the planner alone is worth without the learnt table;
* `vfh_local` (likewise): the VFH table on the same local planner, its
  re-planning and motion guard: a reactive follower on the same targets;
* `learnt_rules` (likewise): the learnt table with the hand-written recovery
  rules, when the policy carries a learnt recovery table (`recovery_table`
  metadata, `firmware_py.kinds.sector.decide`): what the learnt recovery
  decisions add. `learnt` uses the file's recovery table when it has one;
  `seek_local` and `vfh_local` always run the hand-written rules.

A learnt policy with `local_planner` metadata (`firmware_py.kinds.sector`)
steers on the robot's local planner: `NavController.local` holds its
parameters, the twin rolls it out with the robot's own planner code
(`nav.planned`), and its `.qtab` carries the episode's map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, cast

import numpy as np

from firmware_py import robot_spec
from firmware_py.background import Background
from firmware_py.kinds.sector import planner_config
from firmware_py.kinds.sector.config import META_KEY as PLANNER_KEY
from firmware_py.kinds.sector.config import LocalPlannerConfig
from firmware_py.kinds.sector.decide import META_KEY as RECOVERY_KEY
from firmware_py.kinds.sector.decide import RecoveryTable, recovery_table
from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.kinds.sector.recoveries import PlannedTarget
from firmware_py.kinds.sector_memory.gridbug import GridBugEncoder
from firmware_py.mapdata import OccupancyGrid
from firmware_py.policy import Policy, load_policy
from ground_station.learn.export import (
    META_GRID,
    geometry_of_map,
    map_grid_rows,
    policy_bytes,
    quantise,
)
from ground_station.learn.sector.evaluate import seek_table

FORWARD, LEFT, RIGHT, REVERSE = range(4)  # robot_spec.ACTION_NAMES order
CONTROLLER_NAMES = ("learnt", "seek", "vfh", "direct")
EXTRA_CONTROLLERS = ("seek_local", "vfh_local", "learnt_rules")  # on request (--controllers), or by default with a local planner


@dataclass
class NavController:
    name: str
    encoder: SectorEncoder
    q: np.ndarray  # float64 (n_states, n_actions); greedy, ties to the lowest index
    guidance: str  # "path" | "direct"
    local: LocalPlannerConfig | None = None  # steer on the robot's local planner (firmware_py.kinds.sector)
    twin: bool = True  # rolled out on the bench's continuous twin too (episodes.run_twin)
    recovery: RecoveryTable | None = None  # learnt recovery decisions (None: the hand-written rules)

    def planner(self, grid: OccupancyGrid, cfg: LocalPlannerConfig, work: Background,
                radius_mm: int) -> PlannedTarget:
        """The tick's side of the local planner this controller drives with (the twin's, nav.planned)."""
        return PlannedTarget(grid, cfg, work, radius_mm, self.recovery)

    def policy(self, map_name: str = "paper10") -> Policy:
        """The table as the robot loads it (int8 .qtab, via the exporter)."""
        qt = quantise(self.q, "int8")
        meta: dict[str, object] = {"controller": self.name, "guidance": self.guidance}
        if self.local is not None:  # the planner needs the map
            meta[META_GRID] = map_grid_rows(map_name)
        if self.local is not None:
            meta[PLANNER_KEY] = self.local.to_metadata()
        if self.recovery is not None:
            meta[RECOVERY_KEY] = self.recovery.to_metadata()
        data = policy_bytes(qt, self.encoder, metadata=meta, map_geometry=geometry_of_map(map_name))
        return load_policy(data)


def vfh_table(encoder: SectorEncoder, steer_mrad: int = 1050, free_bin: int = 1) -> np.ndarray:
    """VFH (Borenstein and Koren 1991) on the encoder's range sectors, as a table.

    The polar histogram is the encoder's sensors' range bins; a direction is
    free when its bin is >= `free_bin` (default: beyond the first edge, so a
    waypoint next to a wall can still be approached). Per state, with the
    target's bearing at its sector's centre:
    * target in the sector ahead: forward if the front is free, else turn
      to the side whose reading is larger (the wider valley);
    * target more than `steer_mrad` to a side: turn toward it (in place);
    * else: the target side's sensor free -> turn toward it; otherwise the
      front free -> forward (the free valley nearest the target is ahead);
      otherwise turn to the side with the larger reading.
    Turning in place cannot hit anything (a disc), so the baseline never
    reverses (no rear sensor in the state). Needs the front sensor (0) in
    the encoder; the side sensors are the ones nearest +-45 deg."""
    sensors = list(encoder.sensors)
    if 0 not in sensors:
        raise ValueError("the VFH baseline needs the front range sensor (0) in the encoder")
    q = np.zeros((encoder.n_states, encoder.n_actions))
    nb = encoder.nbins
    angles = [math.remainder(robot_spec.SENSOR_ANGLES_MRAD[s] / 1000.0, 2 * math.pi) for s in sensors]
    front = sensors.index(0)
    left = min((j for j in range(len(sensors)) if angles[j] > 0), key=lambda j: abs(angles[j] - math.pi / 4),
               default=None)
    right = min((j for j in range(len(sensors)) if angles[j] < 0), key=lambda j: abs(angles[j] + math.pi / 4),
                default=None)
    per = nb ** len(sensors)
    n = encoder.bearing_sectors
    for b in range(n):
        tgt = math.remainder(b * 2.0 * math.pi / n, 2.0 * math.pi)
        toward = LEFT if tgt >= 0 else RIGHT
        for rs in range(per):
            bins = [(rs // nb ** j) % nb for j in range(len(sensors))]  # first sensor least significant
            lb = bins[left] if left is not None else 0
            rb = bins[right] if right is not None else 0
            wider = LEFT if lb >= rb else RIGHT
            front_free = bins[front] >= free_bin
            if b == 0:
                a = FORWARD if front_free else wider
            elif abs(tgt) * 1000.0 > steer_mrad or (lb if toward == LEFT else rb) >= free_bin:
                a = toward
            elif front_free:
                a = FORWARD
            else:
                a = wider
            q[b * per + rs, a] = 1.0
    return q


def policy_table(policy: Policy) -> np.ndarray:
    """The policy's int table as float64 (greedy choices unchanged)."""
    t = np.frombuffer(policy.table.tobytes(), dtype=np.int8 if policy.dtype == "int8" else np.int16)
    return t.reshape(policy.n_states, policy.n_actions).astype(np.float64)


class BenchController(Protocol):
    """What `episodes.run_hil` and `qnav bench nav` need of a controller (NavController, MemoryController)."""

    name: str
    twin: bool

    @property
    def guidance(self) -> str: ...

    @property
    def local(self) -> LocalPlannerConfig | None: ...

    def policy(self, map_name: str = "") -> Policy: ...


MEMORY_CONTROLLER_NAMES = ("learnt", "rule")  # a sector-memory policy's: its table, the hand-written rule


@dataclass
class MemoryController:
    """A `sector-memory` table in the direct setting (the goal alone; the robot localises and keeps
    its wall memory on its own map): HIL only, as `NavController` for `episodes.run_hil`. Its
    trainer's twin is a grid world without the scenario's continuous discs and movers, so the
    bench has no twin figure for it. `rule` is the hand-written table of the same mode rules
    (`learn.sector_memory.trainer.hand_table`): what learning the moves adds."""

    name: str
    table: Policy
    guidance: str = "direct"
    local: LocalPlannerConfig | None = None
    twin: bool = False

    def policy(self, map_name: str = "") -> Policy:
        """The .qtab the robot runs (map-agnostic: the rig gives the robot the episode's map)."""
        return self.table


def memory_controllers(policy: Policy, names: tuple[str, ...] = MEMORY_CONTROLLER_NAMES) -> list[MemoryController]:
    """learnt / rule for a sector-memory policy."""
    from ground_station.learn.sector_memory.trainer import hand_table

    bad = [n for n in names if n not in MEMORY_CONTROLLER_NAMES]
    if bad:
        raise ValueError(f"a sector-memory policy runs the controllers {', '.join(MEMORY_CONTROLLER_NAMES)}, "
                         f"not {', '.join(bad)}")
    out = []
    for n in names:
        if n == "learnt":
            out.append(MemoryController(n, policy))
            continue
        qt = quantise(hand_table(cast(GridBugEncoder, policy.encoder)), "int8")
        data = policy_bytes(qt, policy.encoder, metadata={**policy.metadata, "controller": "rule"},
                            map_geometry=policy.map_geometry)
        out.append(MemoryController(n, load_policy(data)))
    return out


def kind_controllers(policy: Policy, names: tuple[str, ...] | None = None) -> list[BenchController]:
    """The bench's controllers for the policy's kind (names None: the kind's defaults)."""
    if policy.kind == "sector-memory":
        return list(memory_controllers(policy, names or MEMORY_CONTROLLER_NAMES))
    return list(standard_controllers(policy, names or CONTROLLER_NAMES))


def standard_controllers(policy: Policy, names: tuple[str, ...] = CONTROLLER_NAMES) -> list[NavController]:
    """learnt / seek / vfh / direct (and seek_local, vfh_local) on the learnt policy's encoder."""
    if policy.kind != "sector":
        raise ValueError(f"bench nav needs a sector policy or a sector-memory policy, got a {policy.kind} policy")
    known = CONTROLLER_NAMES + EXTRA_CONTROLLERS
    bad = [n for n in names if n not in known]
    if bad:
        raise ValueError(f"unknown {', '.join(bad)}; a sector policy runs {', '.join(known)}")
    enc = cast(SectorEncoder, policy.encoder)
    q = policy_table(policy)
    local = planner_config(policy)
    rec = recovery_table(policy.metadata)
    make = {
        "learnt": lambda: NavController("learnt", enc, q, "path", local, recovery=rec),
        "learnt_rules": lambda: NavController("learnt_rules", enc, q, "path", local or LocalPlannerConfig()),
        "vfh_local": lambda: NavController("vfh_local", enc, vfh_table(enc), "path",
                                           local or LocalPlannerConfig()),
        "seek_local": lambda: NavController("seek_local", enc, seek_table(enc), "path",
                                            local or LocalPlannerConfig()),
        "seek": lambda: NavController("seek", enc, seek_table(enc), "path"),
        "vfh": lambda: NavController("vfh", enc, vfh_table(enc), "path"),
        "direct": lambda: NavController("direct", enc, q, "direct"),
    }
    return [make[n]() for n in names]


def with_recovery_table(policy: str, table: RecoveryTable, record: dict | None = None) -> bytes:
    """The sector policy file `policy` (a path or policies:NAME) with `table` as its recovery
    decisions (`recovery_table` metadata) and the training record (`recovery_training`)."""
    from firmware_py.shipped_policies import resolve_policy_spec
    from ground_station.learn.export import with_metadata

    pol = load_policy(str(resolve_policy_spec(policy)))
    if planner_config(pol) is None:
        raise ValueError(f"{policy}: a recovery table needs a sector policy with a local planner")
    meta = {**pol.metadata, RECOVERY_KEY: table.to_metadata()}
    if record is not None:
        meta["recovery_training"] = record
    return with_metadata(pol, meta)
