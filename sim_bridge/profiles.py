"""Named plant profiles: the wheel and sensor error a HIL run is judged under.

`ideal` is the plant as it always ran in the benchmarks (perfect encoders, 10 mm range noise, no
dropout). `realistic` is what a small real robot shows every day, and the one the localisation
acceptance uses: one wheel's encoder reads 3 % long (a worn or slightly different wheel), 10 %
random slip on both wheels, 10 mm range noise and 2 % dropout. `qnav-sim --profile`, `qnav bench hil
--profile` (and `qnav bench nav --profile`) take these names; every field is also a separate
`qnav-sim` option.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any


@dataclass(frozen=True)
class PlantProfile:
    name: str
    encoder_scale: tuple[float, float] = (1.0, 1.0)  # (left, right) measured / true wheel travel
    slip_std: float = 0.0  # per-physics-step Gaussian slip of each wheel's measured travel (fraction)
    range_noise_mm: float = 10.0  # std dev of range noise
    range_dropout: float = 0.0  # probability that a reading is INVALID

    def __post_init__(self) -> None:
        if not all(0.5 <= s <= 1.5 for s in self.encoder_scale):
            raise ValueError(f"encoder scale {self.encoder_scale} outside 0.5..1.5")
        if self.slip_std < 0 or self.range_noise_mm < 0 or not 0 <= self.range_dropout <= 1:
            raise ValueError("slip and noise must be >= 0, dropout in [0, 1]")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


PROFILES: dict[str, PlantProfile] = {
    "ideal": PlantProfile("ideal"),
    "realistic": PlantProfile("realistic", encoder_scale=(1.03, 1.0), slip_std=0.10, range_noise_mm=10.0,
                              range_dropout=0.02),
}


def profile(name: str) -> PlantProfile:
    """A profile by name; ValueError (one line) naming the known ones."""
    try:
        return PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown plant profile {name!r}; known: {', '.join(PROFILES)}") from None
