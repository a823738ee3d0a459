"""The sector kind's `local_planner` metadata: the local planner's parameters
(`LocalPlannerConfig`, mm and us), each checked by `from_metadata` (a ValueError
naming the field), and the bound on the search (`MAX_WINDOW_CELLS`). The kind
reads it from a policy's metadata (`firmware_py.kinds.sector.parse_metadata`,
stored as `policy.kind_config`); the exporter writes `to_metadata()`.

The body clearances (`BODY_FIELDS`: wall_clear_mm, obstacle_clear_mm, soft_mm,
los_clear_mm) are stated for the built-in robot's body (`robot_spec.ROBOT_RADIUS_MM`
plus a margin, as every file records them); a robot of another body
(`firmware_py.layout.Layout.robot_radius_mm`, from its profile) keeps the same
margins round its own: `for_body(radius_mm)`, which the sector kind applies.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from firmware_py import robot_spec
from firmware_py.mapdata import MAP_MARGIN_MM

META_KEY = "local_planner"  # policy metadata: the planner's parameters (an object; {} = the defaults)
MAX_WINDOW_CELLS = 200  # raster cells a side of the search window
BODY_FIELDS = ("wall_clear_mm", "obstacle_clear_mm", "soft_mm", "los_clear_mm")  # the body's radius + a margin


@dataclass(frozen=True)
class LocalPlannerConfig:
    """The planner's parameters (mm, us); `from_metadata` checks each."""

    margin_mm: int = MAP_MARGIN_MM
    see_mm: int = 1500  # readings farther than this are not remembered (the fan is wide out there)
    memory_us: int = 3_000_000  # a point not seen again for this long is forgotten
    max_points: int = 400
    raster_mm: int = 100
    wall_clear_mm: int = robot_spec.ROBOT_RADIUS_MM + 25
    obstacle_clear_mm: int = robot_spec.ROBOT_RADIUS_MM + 40
    soft_mm: int = robot_spec.ROBOT_RADIUS_MM + 200
    weight: int = 3
    los_clear_mm: int = robot_spec.ROBOT_RADIUS_MM + 100
    window_mm: int = 1000
    lookahead_mm: int = 600
    max_plan_mm: int = 3000  # no planning toward a waypoint farther than this (bounds the tick's work)
    # the motion guard (MotionGuard): no forward step into a reading this near ...
    veto_mm: int = 40
    # ... and backing off when the robot has not moved stuck_mm for stuck_us next to a remembered point
    stuck_mm: int = 50
    stuck_us: int = 2_000_000
    backoff_us: int = 500_000
    backoff_near_mm: int = 100  # the point within robot radius + this
    rear_clear_mm: int = 250  # the rear sensor must read at least this ...
    rear_side_clear_mm: int = 120  # ... and the rear diagonals at least this
    # a reading this much longer than the distance to a remembered point inside its cone clears the
    # point (nav2's obstacle layer clears by raytracing: a mover that walked on leaves no wall behind)
    clear_margin_mm: int = 150
    # recoveries when the local route is closed (Recovery): stand still this long for a mover ...
    wait_us: int = 2_000_000
    # ... the points that closed it are kept this long (unless a reading sees through them) while the
    # robot re-plans globally round them, so a detour through another door does not turn back ...
    route_memory_us: int = 60_000_000
    # ... and after this many global re-plans without a route: "no route" (round r waits r x wait_us:
    # a mover in the only corridor walks off in a few seconds, a box in a door stays)
    max_rounds: int = 3
    # a round whose wait saw more new points than this was a moving scene (a mover in the only way):
    # it does not count toward "no route" (at most 3 x max_rounds rounds in all)
    moving_points: int = 8
    # a whole-map search without a route that only what came in during the round's wait closes (a person
    # who walked into the only corridor): the route without it is driven this long first (recoveries)
    approach_us: int = 10_000_000

    @classmethod
    def from_metadata(cls, meta: Any) -> LocalPlannerConfig:
        """The config in a policy's metadata value; ValueError with one line naming the bad field."""
        if not isinstance(meta, dict):
            raise ValueError(f"{META_KEY} is not a JSON object")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(meta) - known)
        if unknown:
            raise ValueError(f"{META_KEY}: unknown field {unknown[0]!r}")
        for k, v in meta.items():
            if not isinstance(v, int) or isinstance(v, bool) or not 0 < v <= 100_000_000:
                raise ValueError(f"{META_KEY}.{k} = {v!r} is not a positive integer")
        cfg = cls(**meta)
        if not 50 <= cfg.raster_mm <= 500:
            raise ValueError(f"{META_KEY}.raster_mm = {cfg.raster_mm} (allowed 50..500)")
        for name in ("margin_mm", "wall_clear_mm", "obstacle_clear_mm"):  # bound the per-point work
            if getattr(cfg, name) > 1000:
                raise ValueError(f"{META_KEY}.{name} = {getattr(cfg, name)} (allowed up to 1000)")
        if not cfg.obstacle_clear_mm <= cfg.los_clear_mm <= cfg.soft_mm:
            raise ValueError(f"{META_KEY}: need obstacle_clear_mm <= los_clear_mm <= soft_mm")
        if cfg.backoff_us >= cfg.stuck_us:
            raise ValueError(f"{META_KEY}: need backoff_us < stuck_us")
        if (cfg.max_points > 1000 or cfg.window_mm > 5000 or cfg.soft_mm > 2000 or cfg.max_plan_mm > 10_000
                or cfg.lookahead_mm > 5000):
            raise ValueError(f"{META_KEY}: max_points <= 1000, window_mm <= 5000, soft_mm <= 2000, "
                             "max_plan_mm <= 10000 and lookahead_mm <= 5000")
        if (cfg.max_rounds > 10 or cfg.clear_margin_mm > 1000 or cfg.wait_us > 30_000_000
                or cfg.approach_us > 60_000_000):
            raise ValueError(f"{META_KEY}: max_rounds <= 10, clear_margin_mm <= 1000, wait_us <= 30000000 and "
                             "approach_us <= 60000000")
        if cfg.soft_mm // cfg.raster_mm > 5:  # each point grows into (2 k + 3)^2 raster cells
            raise ValueError(f"{META_KEY}: soft_mm is more than 5 raster cells ({cfg.soft_mm} / {cfg.raster_mm})")
        side = (cfg.max_plan_mm + 2 * cfg.window_mm) // cfg.raster_mm
        if side > MAX_WINDOW_CELLS:  # the search's size in cells, whatever the millimetres say
            raise ValueError(f"{META_KEY}: the search window is {side} raster cells a side "
                             f"((max_plan_mm + 2 window_mm) / raster_mm; allowed up to {MAX_WINDOW_CELLS})")
        return cfg

    def for_body(self, radius_mm: int) -> LocalPlannerConfig:
        """The config for a body of `radius_mm` (the robot's profile): the body clearances keep their
        margins beyond it (the recorded values are the built-in body's plus the margin)."""
        shift = radius_mm - robot_spec.ROBOT_RADIUS_MM
        if shift == 0:
            return self
        return replace(self, **{name: max(1, getattr(self, name) + shift) for name in BODY_FIELDS})

    def to_metadata(self) -> dict[str, int]:
        return asdict(self)
