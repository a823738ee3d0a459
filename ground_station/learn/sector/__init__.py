"""The `sector` kind's training: the kinematic twin (`twin`), its shaped reward
(`reward`), the jitted training and rollout kernels (`kernels`), the trainer
(`trainer`) and greedy evaluation (`evaluate`).

This module is the kind's front door for the registry (`ground_station.learn.kinds`):
its options, their checks and `KIND`, without numba."""

from __future__ import annotations

from dataclasses import dataclass

from firmware_py.kinds.sector.encoder import SectorEncoder
from ground_station.learn.cell import LEARNERS
from ground_station.learn.kinds import TrainingKind, option

GUIDANCES = ("path", "direct")


@dataclass
class SectorOptions:
    """What only sector training reads (flags --sector-*)."""

    guidance: str = option("path", "path = steer to the ground station's planned waypoints (ground_station/maps/"
                                   "planner.py; the robot gets them as a mission), direct = steer to the goal's "
                                   "bearing only")
    bearing_sectors: int = option(15, "goal-bearing sectors (odd: no sector straddles straight behind)")
    sensors: str = option("0,1,7", "comma-separated range sensor indices in the state")
    range_edges: str = option("100,400", "comma-separated ascending range bin edges (mm)")
    margin_mm: float = option(75.0, "clearance beyond the robot radius a pruned waypoint segment keeps")
    max_segment_mm: float = option(1000.0, "longest waypoint segment (mm); 0 = no limit")
    align_reward: float = option(1.0, "shaping reward per pi rad the target's bearing turns toward ahead")
    progress_reward: float = option(1.0, "reward per cell of progress along the guide potential (remaining "
                                         "waypoint path, or the goal's octile field when direct)")
    reverse_cost: float = option(0.02, "extra cost per control period spent reversing (the robot has no rear "
                                       "range sensor in the state)")
    hold_max: int = option(100, "control periods a chosen action is held while the state is unchanged, learnt "
                                "as one semi-Markov transition; 1 = plain one-step updates")
    lr_end: float = option(0.005, "learning rate at the last step (linear from --lr); = --lr for a constant rate")
    range_noise_mm: float = option(10.0, "std (mm) of Gaussian noise on the range readings the learner sees (the "
                                         "sim's sensor noise); 0 = exact readings")
    maps: str = option("", "extra comma-separated training maps (names or generator specs) besides --map")


def int_list(text: str, name: str) -> tuple[int, ...]:
    """'1,2,3' -> (1, 2, 3); ValueError naming the field otherwise."""
    try:
        return tuple(int(v) for v in str(text).split(",") if v.strip())
    except ValueError:
        raise ValueError(f"{name} must be comma-separated integers, got {text!r}") from None


def validate(cfg) -> None:  # type: ignore[no-untyped-def]
    o: SectorOptions = cfg.options
    if o.guidance not in GUIDANCES:
        raise ValueError(f"sector_guidance must be path or direct, got {o.guidance!r}")
    if o.hold_max < 1:
        raise ValueError(f"sector_hold_max must be >= 1, got {o.hold_max}")
    if not 0.0 <= o.lr_end <= 1.0:
        raise ValueError(f"sector_lr_end must be in [0, 1], got {o.lr_end}")
    if o.margin_mm < 0 or o.max_segment_mm < 0 or o.range_noise_mm < 0:
        raise ValueError("sector_margin_mm, sector_max_segment_mm and sector_range_noise_mm must be >= 0")
    if not int_list(o.sensors, "sector_sensors"):
        raise ValueError("sector_sensors must name at least one sensor")
    int_list(o.range_edges, "sector_range_edges")
    from ground_station.learn.robot import check_profile_fits

    check_profile_fits(cfg, sector_encoder(cfg))


def sector_encoder(cfg) -> SectorEncoder:  # type: ignore[no-untyped-def]
    """The reference SectorEncoder a config trains (its sector_* fields)."""
    return SectorEncoder(bearing_sectors=int(cfg.options.bearing_sectors),
                         sensors=int_list(cfg.options.sensors, "sector_sensors"),
                         range_edges_mm=int_list(cfg.options.range_edges, "sector_range_edges"))


def encoder_from_dict(d: dict) -> SectorEncoder:
    return SectorEncoder(bearing_sectors=int(d["bearing_sectors"]), sensors=tuple(int(s) for s in d["sensors"]),
                         range_edges_mm=tuple(int(e) for e in d["range_edges_mm"]))


KIND = TrainingKind(
    name="sector", summary="goal-bearing sector x range bins on the kinematic twin", options=SectorOptions,
    prefix="sector_", train="ground_station.learn.sector.trainer:train_sector",
    evaluate="ground_station.learn.sector.evaluate:evaluate_policy", encoder_from_dict=encoder_from_dict,
    learners=LEARNERS, validate=validate,
    recipe={"steps": 20_000_000, "lr": 0.1, "gamma": 0.95, "reward_step": 0.0, "epsilon_end": 0.05})
