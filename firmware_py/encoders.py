"""Reference state encoders: the one definition of how observations become a
Q-table row index.

Training (ground_station) uses a jitted copy of `SectorEncoder.encode`; a
test proves the copy equals this reference on many random inputs. Everything
here is integer arithmetic so the robot's control path stays int-only.

* `CellEncoder`: state = goal_index * (W * H) + row * W + col (the paper's grid).
* `SectorEncoder`: state = bearing_sector * nbins**k + sum(bin_i * nbins**i)
  over the k sensors it uses, where bearing_sector is the goal bearing
  relative to the heading quantised into `bearing_sectors` sectors (sector 0
  centred straight ahead, counting counter-clockwise) and bin_i is the number
  of `range_edges_mm` at or below sensor i's range.

The cell-stepped Bug memory encoder of `sector-memory` policies lives in
`firmware_py.kinds.sector_memory.gridbug`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from firmware_py import robot_spec

TWO_PI_MRAD = 6283  # 2*pi in milliradians, rounded


def bearing_sector(bearing_mrad: int, sectors: int) -> int:
    """Quantise a relative bearing (mrad, any range) into `sectors` sectors,
    sector 0 centred on straight ahead, increasing counter-clockwise."""
    b = bearing_mrad % TWO_PI_MRAD
    return ((2 * b * sectors + TWO_PI_MRAD) // (2 * TWO_PI_MRAD)) % sectors


@dataclass(frozen=True)
class SectorEncoder:
    """Goal-bearing sector x binned ranges of selected sensor sectors."""

    bearing_sectors: int = 8
    sensors: tuple[int, ...] = (0, 1, 2, 6, 7)  # indices into robot_spec.SENSOR_ANGLES_MRAD
    range_edges_mm: tuple[int, ...] = (350, 700)  # ascending; len + 1 bins
    kind: str = field(default="sector", init=False)

    def __post_init__(self) -> None:
        if self.bearing_sectors < 1:
            raise ValueError("bearing_sectors must be >= 1")
        if not self.sensors or any(not 0 <= s < robot_spec.SENSOR_COUNT for s in self.sensors):
            raise ValueError(f"sensor indices must be in 0..{robot_spec.SENSOR_COUNT - 1}")
        if list(self.range_edges_mm) != sorted(set(self.range_edges_mm)):
            raise ValueError("range_edges_mm must be strictly ascending")

    @property
    def nbins(self) -> int:
        return len(self.range_edges_mm) + 1

    @property
    def n_states(self) -> int:
        range_states: int = self.nbins ** len(self.sensors)  # int ** int is typed Any
        return self.bearing_sectors * range_states

    @property
    def n_actions(self) -> int:
        return len(robot_spec.ACTION_WHEEL_SPEEDS_MM_S)

    def range_bin(self, range_mm: int, status: int = robot_spec.RANGE_VALID) -> int:
        if status == robot_spec.RANGE_TOO_CLOSE:
            return 0
        if status != robot_spec.RANGE_VALID:  # too far or invalid: nothing seen
            return self.nbins - 1
        b = 0
        for edge in self.range_edges_mm:
            if range_mm >= edge:
                b += 1
        return b

    def encode(self, bearing_mrad: int, ranges_mm: list[int] | tuple[int, ...],
               status: list[int] | tuple[int, ...] | None = None) -> int:
        """State index from the goal bearing and all SENSOR_COUNT ranges."""
        state = 0
        mult = 1
        nb = self.nbins
        for s in self.sensors:
            st = robot_spec.RANGE_VALID if status is None else status[s]
            state += self.range_bin(ranges_mm[s], st) * mult
            mult *= nb
        return bearing_sector(bearing_mrad, self.bearing_sectors) * mult + state

    def to_dict(self) -> dict[str, object]:
        d = asdict(self)
        d["sensors"] = list(self.sensors)
        d["range_edges_mm"] = list(self.range_edges_mm)
        return d


@dataclass(frozen=True)
class CellEncoder:
    """Robot cell on a W x H grid, times the goal index when there are several."""

    width: int
    height: int
    n_goals: int = 1
    kind: str = field(default="cell", init=False)

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1 or self.n_goals < 1:
            raise ValueError("width, height and n_goals must be >= 1")

    @property
    def n_states(self) -> int:
        return self.width * self.height * self.n_goals

    @property
    def n_actions(self) -> int:
        return len(robot_spec.CELL_ACTION_DELTAS)

    def encode(self, col: int, row: int, goal_index: int = 0) -> int:
        if not (0 <= col < self.width and 0 <= row < self.height and 0 <= goal_index < self.n_goals):
            raise ValueError(f"cell ({col},{row}) goal {goal_index} outside the {self.width}x{self.height}x{self.n_goals} grid")
        return (goal_index * self.height + row) * self.width + col

    def to_dict(self) -> dict[str, object]:
        return asdict(self)


def best_action(row: list[int] | tuple[int, ...] | memoryview) -> int:
    """Greedy action of one Q-table row; ties break to the lowest index."""
    best = 0
    best_v = row[0]
    for i in range(1, len(row)):
        if row[i] > best_v:
            best_v = row[i]
            best = i
    return best
