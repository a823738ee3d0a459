"""The sector kind's reference state encoder: the one definition of how a goal
bearing and range readings become a Q-table row index.

state = bearing_sector * nbins**k + sum(bin_i * nbins**i) over the k sensors it
uses, where bearing_sector is the goal bearing relative to the heading quantised
into `bearing_sectors` sectors (sector 0 centred straight ahead, counting
counter-clockwise) and bin_i is the number of `range_edges_mm` at or below
sensor i's range. Integer arithmetic only, so the robot's control path stays
int-only. Training (ground_station.learn.sector.twin) uses a jitted copy of
`SectorEncoder.encode`; a test proves the copy equals this reference on many
random inputs.
"""

from __future__ import annotations

from bisect import bisect_right
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
        return bisect_right(self.range_edges_mm, range_mm)  # the edges at or below the range

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
