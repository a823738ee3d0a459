"""Maps addressable by name.

* Files shipped in `ground_station/maps_data/` (`paper10`, the public
  MovingAI maps `random-32-32-20`, `room-32-32-4`), each `.map` with an
  optional `<name>.targets.json` sidecar holding its targets.
* Generator specs `KIND-WxH-sSEED` with KIND in random, rooms, trap, maze,
  e.g. `trap-16x16-s3` (generators use their default parameters).
"""

from __future__ import annotations

import re
from importlib import resources
from pathlib import Path

from ground_station.maps.grid import GridMap, MapError
from ground_station.maps.movingai import parse_map, parse_targets, read_map

_SPEC = re.compile(r"^(random|rooms|trap|maze)-(\d+)x(\d+)-s(\d+)$")


def _data_dir():
    return resources.files("ground_station") / "maps_data"


def builtin_names() -> list[str]:
    """Names of the map files shipped with the package."""
    return sorted(p.name[:-4] for p in _data_dir().iterdir() if p.name.endswith(".map"))


def load_builtin(name: str, cell_size_m: float = 0.5) -> GridMap:
    d = _data_dir()
    f = d / f"{name}.map"
    if not f.is_file():
        raise MapError(f"unknown map {name!r}; built-in: {', '.join(builtin_names())} "
                       "or a generator spec like trap-16x16-s0 (random|rooms|trap|maze)")
    gm = parse_map(f.read_text(), name=name, cell_size_m=cell_size_m)
    t = d / f"{name}.targets.json"
    if t.is_file():
        gm = GridMap(name, gm.occ, parse_targets(t.read_text(), name=f"{name}.targets.json"), cell_size_m)
    return gm


def load_map(name_or_path: str, cell_size_m: float = 0.5) -> GridMap:
    """A built-in map by name, a generator spec, or a path to a `.map` file.

    Raises MapError (one line) on unknown names and malformed files."""
    s = str(name_or_path)
    m = _SPEC.match(s)
    if m:
        # numba's generators only here: reading a map file needs none (ground_station.maps)
        from ground_station.maps.generate import GENERATORS

        kind, w, h, seed = m.group(1), int(m.group(2)), int(m.group(3)), int(m.group(4))
        gm = GENERATORS[kind](w, h, seed=seed, name=s)
        gm.cell_size_m = cell_size_m
        return gm
    p = Path(s)
    if s.endswith(".map") or p.exists() or "/" in s:
        return read_map(p, cell_size_m=cell_size_m)
    return load_builtin(s, cell_size_m=cell_size_m)
