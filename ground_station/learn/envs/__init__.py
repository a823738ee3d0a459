"""Gymnasium training environments, registered with versioned ids.

* `qnav/CellNav-v0`: `CellNavEnv` on `paper10`, all targets, TimeLimit 100.
* `qnav/SectorNav-v0`: `SectorNavEnv` (kinematic twin) on `paper10`, random goals, TimeLimit 1000.

`gymnasium.make("qnav/CellNav-v0", gridmap=..., targets=...)` overrides the
defaults. Registration happens on import of this package.
"""

from gymnasium.envs.registration import register, registry

from ground_station.learn.envs.cell_env import CellNavEnv


def _register(env_id: str, entry_point: str, **kwargs) -> None:
    if env_id not in registry:
        register(id=env_id, entry_point=entry_point, **kwargs)


_register("qnav/CellNav-v0", "ground_station.learn.envs.cell_env:CellNavEnv", max_episode_steps=100)
_register("qnav/SectorNav-v0", "ground_station.learn.envs.sector_env:SectorNavEnv", max_episode_steps=1000)

__all__ = ["CellNavEnv"]
