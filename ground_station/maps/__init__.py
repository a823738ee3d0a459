"""Grid maps: the `GridMap` model, MovingAI `.map`/`.scen` I/O, shortest
distances (BFS 4-connected, octile 8-connected), seeded generators and
built-in maps by name (`paper10` with targets A-D)."""

from ground_station.maps.builtin import builtin_names, load_map
from ground_station.maps.distances import bfs_distances, octile_distances
from ground_station.maps.generate import maze_map, random_map, rooms_map, trap_map
from ground_station.maps.grid import GridMap, MapError
from ground_station.maps.movingai import (
    Scenario,
    dump_map,
    parse_map,
    read_map,
    read_scen,
    write_map,
)

__all__ = [
    "GridMap", "MapError", "Scenario", "bfs_distances", "builtin_names", "dump_map", "load_map",
    "maze_map", "octile_distances", "parse_map", "random_map", "read_map", "read_scen",
    "rooms_map", "trap_map", "write_map",
]
