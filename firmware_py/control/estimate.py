"""Estimation, one part of the controller: the dead-reckoning pose (`Odometry`, from encoder samples
the plausibility check lets through) and, on a map, the Monte Carlo localiser's pose
(control/localiser.py) the robot drives by.

Its inputs, and nothing else (docs/architecture.md, "The robot controller"): `encoders` and
`localise_tick` per tick, the map via `new_localiser` (off the lock) then `use`. It decides nothing:
the controller reads `nav` and the verdicts it returns.
"""

from __future__ import annotations

from firmware_py import robot_spec
from firmware_py.can_protocol import ENCODER_BITS
from firmware_py.control.io import Inputs
from firmware_py.control.localiser import Localiser, LocaliserConfig
from firmware_py.control.odometry import Odometry
from firmware_py.control.plausibility import encoder_jump
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.layout import Layout
from firmware_py.mapdata import OccupancyGrid, unmapped_readings


class PoseEstimate:
    """Odometry, the encoder plausibility check and the localiser (module docstring)."""

    def __init__(self, start_pose_mm: tuple[int, int, int] = (0, 0, 0), *, localise: bool = True,
                 localiser_config: LocaliserConfig | None = None, layout: Layout = DEFAULT_LAYOUT) -> None:
        self.layout = layout  # the wheels, counts and sensors (firmware_py.layout, from the robot profile)
        self.odom = Odometry(*start_pose_mm, ticks_per_rev=layout.counts_per_rev, wheel_radius_mm=layout.wheel_radius_mm,
                             wheel_base_mm=layout.wheel_base_mm, counter_bits=ENCODER_BITS)
        self.localise = localise  # False: dead reckoning alone (qnav-robot --localiser off)
        self.loc_cfg = localiser_config
        self.loc: Localiser | None = None
        self.encoder_jumps = 0  # implausible encoder samples (not integrated)
        self._last_enc_us: int | None = None

    @property
    def nav(self) -> Localiser | Odometry:
        """The pose the robot drives by: the localiser's when it runs, else odometry."""
        return self.loc if self.loc is not None else self.odom

    # --- the map ------------------------------------------------------------------------------
    def new_localiser(self, grid: OccupancyGrid | None) -> Localiser | None:
        """A localiser for `grid` when the running one is for another map (None: keep the running
        one, or there is no map). Building one precomputes its likelihood field, so callers run it
        outside the controller's lock: the ticks keep going."""
        grid = grid if self.localise else None
        cur = self.loc
        if grid is None or (cur is not None and cur.grid == grid):
            return None
        return Localiser(grid, self.loc_cfg, layout=self.layout)

    def use(self, grid: OccupancyGrid | None, new: Localiser | None) -> None:
        """Under the lock: switch to `new` (started at the odometry pose), keep the running one for
        the same map, or drop it (no map: odometry alone)."""
        if grid is None or not self.localise:
            self.loc = None
        elif new is not None and (self.loc is None or self.loc.grid != new.grid):
            new.init_pose(*self.odom.pose_mm())
            self.loc = new

    # --- the tick -------------------------------------------------------------------------------
    def encoders(self, inp: Inputs) -> str:
        """Take a new encoder sample (if one came): integrated, or, when implausible, taken as the
        new reference without moving the pose. Returns why it was implausible ("" if it was not)."""
        if inp.enc_us is None or inp.enc_us == self._last_enc_us:
            return ""
        why = ""
        d = self.odom.deltas(inp.enc_left, inp.enc_right)
        if d is not None and self._last_enc_us is not None:
            why = encoder_jump(d, max(0, inp.enc_us - self._last_enc_us), self.layout)
        if why:
            self.encoder_jumps += 1
            self.odom.rebase(inp.enc_left, inp.enc_right, inp.enc_us)  # the pose stays put
        else:
            self.odom.update(inp.enc_left, inp.enc_right, inp.enc_us)
        self._last_enc_us = inp.enc_us
        return why

    def statuses(self, inp: Inputs, withhold_mm: int | None) -> list[int]:
        """The range statuses the localiser weighs: with `withhold_mm` (the active policy's margin,
        None: weigh all), readings its map does not explain at the tracked pose (unmapped obstacles)
        are withheld as invalid: each lowers every particle's weight, and a few together would start
        augmented MCL's random-particle recovery, which in a map of look-alike places jumps the estimate."""
        status = list(inp.range_status)
        loc = self.loc
        if withhold_mm is None or loc is None or not loc.localised:
            return status
        um = unmapped_readings(loc.grid, *loc.pose_mm(), inp.ranges_mm, status, withhold_mm,
                               None if self.layout == DEFAULT_LAYOUT else self.layout)
        return [robot_spec.RANGE_INVALID if u >= 0 else st for u, st in zip(um, status, strict=True)]

    def localise_tick(self, inp: Inputs, withhold_mm: int | None) -> str:
        """One localiser tick on the odometry pose and the readings; "localised" or "localisation
        lost" when that changed, else ""."""
        loc = self.loc
        if loc is None:
            return ""
        was = loc.localised
        loc.tick(self.odom.pose_mm(), inp.ranges_mm, self.statuses(inp, withhold_mm))
        if loc.localised == was:
            return ""
        return "localised" if loc.localised else "localisation lost"
