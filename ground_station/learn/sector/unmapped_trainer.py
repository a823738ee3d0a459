"""Q-learning of a `sector-unmapped` table on the obstacle scenario pool.

`UnmappedSectorTrainer` is `ObstacleSectorTrainer` (same seeded pool over
the training maps with 0..K discs and 0..M movers, same TrainConfig fields:
lr schedule, epsilon, gamma, reward, holds, range noise, start jitter) with
the kernel `unmapped.obs_unmapped_train_kernel`: the robot's detour memory
on readings the map does not explain. `frozen` (bool per state) keeps rows
as they are, by default the go rows (the shipped sector table, so the
policy without obstacles stays the shipped one); `stall_steps` /
`stall_cost` end a stalled training episode as a failure (the bench's loop
rule). Same `run(q, start_step, n_steps) -> (returns, successes)`.
"""

from __future__ import annotations

import numpy as np

from firmware_py.unmapped import UnmappedSectorEncoder
from ground_station.learn.config import TrainConfig
from ground_station.learn.sector.obstacle_trainer import ObstacleSectorTrainer
from ground_station.learn.sector.reward import SectorReward
from ground_station.learn.sector.twin import RADIUS_MM, encoder_arrays
from ground_station.learn.sector.unmapped import obs_unmapped_train_kernel, unmapped_params
from ground_station.maps import GridMap


class UnmappedSectorTrainer(ObstacleSectorTrainer):
    """Exact sequential Q-learning of an UnmappedSectorEncoder table on a scenario pool."""

    def __init__(self, maps: list[GridMap], cfg: TrainConfig, encoder: UnmappedSectorEncoder,
                 reward: SectorReward | None = None) -> None:
        super().__init__(maps, cfg, encoder.base, reward)
        self.encoder = encoder  # type: ignore[assignment]
        self.n_states = encoder.n_states
        self._up, self._dsens, _ = unmapped_params(encoder)
        sectors, sensors, edges, _ = encoder_arrays(encoder.base)
        self._base = (sectors, sensors, edges)
        self.frozen = np.zeros(encoder.n_states, dtype=np.bool_)
        self.frozen[:encoder.n_go] = True
        self.fields = np.zeros((0, 1, 1), dtype=np.float64)  # shape_with_cspace: privileged progress
        self.raster_mm = 100.0

    def shape_with_cspace(self, raster_mm: float = 100.0, clear_mm: float = RADIUS_MM + 25.0) -> None:
        """Pay progress on each pool episode's configuration-space path length
        to its goal (discs included; `nav.scenario._cspace`, robot radius +
        clear margin) instead of the straight line to the waypoint: going round
        a disc is then progress. Training only; the state is unchanged."""
        from ground_station.nav.diagnose import _dijkstra
        from ground_station.nav.scenario import _cspace

        maps = {gm.name: gm for gm in self.maps}
        shapes = [(int(gm.occ.shape[0] * gm.cell_size_m * 1000 / raster_mm),
                   int(gm.occ.shape[1] * gm.cell_size_m * 1000 / raster_mm)) for gm in self.maps]
        ny = max(s[0] for s in shapes)
        nx = max(s[1] for s in shapes)
        fields = np.full((len(self.pool), ny, nx), np.inf)
        for i, ep in enumerate(self.pool):
            gm = maps[ep.map]
            occ = np.ascontiguousarray(gm.occ, dtype=np.uint8)
            free = _cspace(occ, gm.cell_size_m * 1000.0, np.asarray(ep.discs, dtype=np.float64).reshape(-1, 3),
                           raster_mm, clear_mm)
            gx, gy = ep.waypoints[-1]
            d = _dijkstra(free, int(gx // raster_mm), int(gy // raster_mm))
            fields[i, :d.shape[0], :d.shape[1]] = d
        self.fields = fields
        self.raster_mm = float(raster_mm)

    def run(self, q: np.ndarray, start_step: int, n_steps: int) -> tuple[np.ndarray, np.ndarray]:
        if q.shape != (self.n_states, self.n_actions) or q.dtype != np.float64:
            raise ValueError(f"q must be float64 {(self.n_states, self.n_actions)}, got {q.dtype} {q.shape}")
        a = self.arrays
        cfg = self.cfg
        out_ret = np.empty(n_steps)
        out_succ = np.empty(n_steps, dtype=np.bool_)
        n = obs_unmapped_train_kernel(
            q, self._rng, a["occ"], a["dims"], a["cells"], a["map"], a["start"], a["wp"], a["nwp"], a["rem"],
            a["discs"], a["nd"], a["movers"], a["nm"], *self._base, self._up, self._dsens, self.frozen,
            self.stall_steps, self.stall_cost, self.fields, self.raster_mm, float(cfg.lr), float(cfg.sector_lr_end), float(cfg.gamma),
            *self._eps, self._rw, float(cfg.sector_clear_mm), self.max_episode_steps, int(cfg.sector_hold_max),
            float(cfg.sector_range_noise_mm), self._jitter, int(start_step), int(cfg.steps), int(n_steps),
            out_ret, out_succ)
        return out_ret[:n].copy(), out_succ[:n].copy()
