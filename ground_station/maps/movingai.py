"""MovingAI `.map` / `.scen` text formats, plus the project's target sidecar.

`.map`: header `type octile`, `height H`, `width W`, `map`, then H rows of W
characters (`.` `G` `S` passable; `@` `O` `T` `W` obstacles). Targets live in
a sidecar `<stem>.targets.json` next to the map: a JSON object
`{"A": [col, row], ...}` whose key order is the goal order. `.scen`: the
MovingAI scenario format (`version 1`, then tab-separated bucket, map, width,
height, start x, start y, goal x, goal y, optimal length; x = col, y = row).

Every parse error is a `MapError` with one line naming the file, line and
problem. Writes are atomic (temp file + fsync + os.replace).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_py.atomic import atomic_write
from ground_station.maps.grid import GridMap, MapError

PASSABLE = frozenset(".GS")
OBSTACLE = frozenset("@OTW")
TARGETS_SUFFIX = ".targets.json"


def parse_map(text: str, name: str = "<string>", cell_size_m: float = 0.5) -> GridMap:
    """Parse MovingAI `.map` text (targets are not part of it)."""
    lines = text.splitlines()
    header: dict[str, str] = {}
    i = 0
    expected = ("type", "height", "width")
    for key in expected:
        if i >= len(lines):
            raise MapError(f"{name}: bad header: file ends before '{key}' line")
        parts = lines[i].split()
        if len(parts) != 2 or parts[0].lower() != key:
            raise MapError(f"{name}:{i + 1}: bad header: expected '{key} <value>', got {lines[i]!r}")
        header[key] = parts[1]
        i += 1
    if i >= len(lines) or lines[i].strip().lower() != "map":
        got = lines[i] if i < len(lines) else "end of file"
        raise MapError(f"{name}:{i + 1}: bad header: expected 'map', got {got!r}")
    i += 1
    try:
        height = int(header["height"])
        width = int(header["width"])
    except ValueError:
        raise MapError(f"{name}: bad header: height/width must be integers, got "
                       f"{header['height']!r} x {header['width']!r}") from None
    if height < 1 or width < 1:
        raise MapError(f"{name}: bad header: height and width must be >= 1, got {height} x {width}")
    rows = [ln.rstrip("\r\n") for ln in lines[i:]]
    while rows and not rows[-1].strip():  # tolerate trailing blank lines
        rows.pop()
    if len(rows) != height:
        raise MapError(f"{name}: wrong row count: header says height {height}, found {len(rows)} rows")
    occ = np.zeros((height, width), dtype=bool)
    for r, line in enumerate(rows):
        if len(line) != width:
            raise MapError(f"{name}:{i + r + 1}: wrong width: row {r} has {len(line)} characters, header says {width}")
        for c, ch in enumerate(line):
            if ch in OBSTACLE:
                occ[r, c] = True
            elif ch not in PASSABLE:
                raise MapError(f"{name}:{i + r + 1}: unknown character {ch!r} at column {c} "
                               f"(passable: . G S, obstacle: @ O T W)")
    return GridMap(name=name, occ=occ, targets={}, cell_size_m=cell_size_m)


def dump_map(gridmap: GridMap) -> str:
    """MovingAI `.map` text of a map ('.' free, '@' obstacle)."""
    out = ["type octile", f"height {gridmap.height}", f"width {gridmap.width}", "map"]
    out += ["".join("@" if v else "." for v in row) for row in gridmap.occ]
    return "\n".join(out) + "\n"


def parse_targets(text: str, name: str = "<targets>") -> dict[str, tuple[int, int]]:
    """Parse a targets sidecar: JSON object name -> [col, row]."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise MapError(f"{name}: not valid JSON: {exc.msg} at line {exc.lineno}") from None
    if not isinstance(data, dict):
        raise MapError(f"{name}: expected a JSON object name -> [col, row]")
    out: dict[str, tuple[int, int]] = {}
    for key, val in data.items():
        if (not isinstance(val, list) or len(val) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in val)):
            raise MapError(f"{name}: target {key!r} must be [col, row] integers, got {val!r}")
        out[str(key)] = (val[0], val[1])
    return out


def dump_targets(targets: dict[str, tuple[int, int]]) -> str:
    return json.dumps({k: [int(c), int(r)] for k, (c, r) in targets.items()}, indent=1) + "\n"


def targets_path(map_path: str | Path) -> Path:
    p = Path(map_path)
    return p.with_name(p.stem + TARGETS_SUFFIX)


def read_map(path: str | Path, cell_size_m: float = 0.5) -> GridMap:
    """Read a `.map` file and, if present, its targets sidecar."""
    p = Path(path)
    try:
        text = p.read_text()
    except FileNotFoundError:
        raise MapError(f"{p}: no such map file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MapError(f"{p}: cannot read map: {exc}") from None
    gm = parse_map(text, name=str(p), cell_size_m=cell_size_m)
    tp = targets_path(p)
    if tp.exists():
        targets = parse_targets(tp.read_text(), name=str(tp))
        gm = GridMap(gm.name, gm.occ, targets, cell_size_m)
    return gm


def write_map(path: str | Path, gridmap: GridMap) -> None:
    """Write a `.map` file (atomically) and its targets sidecar if it has targets."""
    p = Path(path)
    atomic_write(p, dump_map(gridmap), make_parents=True)
    if gridmap.targets:
        atomic_write(targets_path(p), dump_targets(gridmap.targets))


@dataclass(frozen=True)
class Scenario:
    """One MovingAI scenario line; positions are (col, row)."""

    bucket: int
    map: str
    width: int
    height: int
    start: tuple[int, int]
    goal: tuple[int, int]
    optimal: float


def parse_scen(text: str, name: str = "<scen>") -> list[Scenario]:
    lines = text.splitlines()
    if not lines or not lines[0].lower().startswith("version"):
        raise MapError(f"{name}:1: bad header: expected 'version 1'")
    out = []
    for n, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        parts = line.split("\t") if "\t" in line else line.split()
        if len(parts) != 9:
            raise MapError(f"{name}:{n}: expected 9 fields, got {len(parts)}")
        try:
            b, w, h, sx, sy, gx, gy = (int(parts[k]) for k in (0, 2, 3, 4, 5, 6, 7))
            opt = float(parts[8])
        except ValueError:
            raise MapError(f"{name}:{n}: non-numeric field in {line!r}") from None
        out.append(Scenario(b, parts[1], w, h, (sx, sy), (gx, gy), opt))
    return out


def read_scen(path: str | Path) -> list[Scenario]:
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise MapError(f"{p}: cannot read scenario file: {exc}") from None
    return parse_scen(text, name=str(p))
