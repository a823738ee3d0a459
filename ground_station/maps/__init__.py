"""Grid maps: the `GridMap` model, MovingAI `.map`/`.scen` I/O, shortest
distances (BFS 4-connected, octile 8-connected), seeded generators and
built-in maps by name (`paper10` with targets A-D).

The distances and generators are numba kernels: they are imported when first
asked for (PEP 562), so a process that only reads a map file (`qnav-sim --map
workshop.map`, `qnav map upload`) does not import numba (0.5 s of CPU a process).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from ground_station.maps.builtin import builtin_names, load_map
from ground_station.maps.grid import GridMap, MapError
from ground_station.maps.movingai import (
    Scenario,
    dump_map,
    parse_map,
    read_map,
    read_scen,
    write_map,
)

if TYPE_CHECKING:
    from ground_station.maps.distances import bfs_distances, octile_distances
    from ground_station.maps.generate import maze_map, random_map, rooms_map, trap_map

_JITTED = {"bfs_distances": "distances", "octile_distances": "distances", "maze_map": "generate",
           "random_map": "generate", "rooms_map": "generate", "trap_map": "generate"}

__all__ = [
    "GridMap", "MapError", "Scenario", "bfs_distances", "builtin_names", "dump_map", "load_map",
    "maze_map", "octile_distances", "parse_map", "random_map", "read_map", "read_scen",
    "rooms_map", "trap_map", "write_map",
]


def __getattr__(name: str) -> Any:
    module = _JITTED.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)
