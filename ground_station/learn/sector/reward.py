"""The shaped reward of the sector task: its terms, and the guidance they follow.

`SectorReward` holds the weights of one control period's reward; its `array()`
is the `rw` vector the jitted `period_step` reads through the `RW_*` indices
below. The trainer and the Gymnasium env both build it from a `TrainConfig`,
so they reward the same thing. The progress term follows the guidance: "path"
the planned waypoints, "direct" the goal's octile field alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ground_station.learn.config import TrainConfig

# slots of the `rw` vector `period_step` reads
RW_PROGRESS, RW_STEP_COST, RW_REVERSE_COST, RW_GOAL, RW_COLLISION, RW_ALIGN = range(6)

GUIDANCES = ("path", "direct")


def check_guidance(guidance: str) -> int:
    """1 for "path", 0 for "direct" (the kernels' `guided` flag); ValueError otherwise."""
    if guidance not in GUIDANCES:
        raise ValueError(f"guidance must be one of {', '.join(GUIDANCES)}, got {guidance!r}")
    return int(guidance == "path")


@dataclass(frozen=True)
class SectorReward:
    """Weights of the shaped reward of one control period (see `period_step`).

    Costs are positive numbers subtracted from the reward; `from_config`
    maps `TrainConfig`'s signed `reward_*` fields onto them."""

    progress: float  # per cell of progress along the guide potential
    step_cost: float  # per control period
    reverse_cost: float  # extra per reverse period (the robot has no rear bumper view)
    goal: float  # on reaching the goal (episode ends)
    collision: float  # the whole reward of a collision is -collision (episode ends)
    align: float  # per pi rad the target's bearing moves toward straight ahead

    @classmethod
    def from_config(cls, cfg: TrainConfig) -> SectorReward:
        """The reward a training config asks for (a sector config: `TrainConfig.of(encoding="sector")` = the defaults)."""
        return cls(progress=float(cfg.options.progress_reward), step_cost=-float(cfg.reward_step),
                   reverse_cost=float(cfg.options.reverse_cost), goal=float(cfg.reward_goal),
                   collision=-float(cfg.reward_collision), align=float(cfg.options.align_reward))

    def array(self) -> np.ndarray:
        """The `rw` vector, indexed by the `RW_*` slots."""
        rw = np.zeros(6)
        rw[[RW_PROGRESS, RW_STEP_COST, RW_REVERSE_COST, RW_GOAL, RW_COLLISION, RW_ALIGN]] = (
            self.progress, self.step_cost, self.reverse_cost, self.goal, self.collision, self.align)
        return rw
