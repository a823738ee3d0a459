"""Seeded map generators: random density, rooms with doors, U-shaped traps,
mazes/corridors. Every generator takes an explicit `seed`, returns a `GridMap` without
targets, and keeps only the largest 4-connected free region (other free
pockets become obstacles), so every free cell can reach every other one.
Same arguments -> same map.
"""

from __future__ import annotations

import numpy as np

from ground_station.maps.distances import bfs_distances
from ground_station.maps.grid import GridMap, MapError


def _keep_largest_region(occ: np.ndarray) -> np.ndarray:
    occ = occ.copy()
    remaining = ~occ
    best = None
    best_n = 0
    while remaining.any():
        r, c = np.argwhere(remaining)[0]
        reach = bfs_distances(occ, int(c), int(r)) >= 0
        n = int(reach.sum())
        if n > best_n:
            best, best_n = reach, n
        remaining &= ~reach
    if best is None:
        raise MapError("generated map has no free cell")
    return ~best


def _check_size(width: int, height: int, minimum: int = 3) -> None:
    if width < minimum or height < minimum:
        raise MapError(f"map size {width}x{height} too small (minimum {minimum}x{minimum})")


def random_map(width: int, height: int, density: float = 0.2, seed: int = 0, name: str | None = None) -> GridMap:
    """Independent obstacles with probability `density` per cell."""
    _check_size(width, height, 2)
    if not 0.0 <= density < 1.0:
        raise MapError(f"density must be in [0, 1), got {density}")
    rng = np.random.default_rng(seed)
    occ = rng.random((height, width)) < density
    return GridMap(name or f"random-{width}x{height}-d{density:g}-s{seed}", _keep_largest_region(occ))


def rooms_map(width: int, height: int, room: int = 4, seed: int = 0, name: str | None = None) -> GridMap:
    """Square rooms of `room` x `room` cells separated by one-cell walls, one
    door in every wall segment between two neighbouring rooms."""
    _check_size(width, height, room + 2)
    if room < 1:
        raise MapError(f"room size must be >= 1, got {room}")
    rng = np.random.default_rng(seed)
    occ = np.zeros((height, width), dtype=bool)
    step = room + 1
    occ[room::step, :] = True
    occ[:, room::step] = True
    # doors: in each horizontal wall row, one gap per room column span; same for vertical
    for wr in range(room, height, step):
        for c0 in range(0, width, step):
            occ[wr, int(rng.choice(range(c0, min(c0 + room, width))))] = False
    for wc in range(room, width, step):
        for r0 in range(0, height, step):
            occ[int(rng.choice(range(r0, min(r0 + room, height)))), wc] = False
    return GridMap(name or f"rooms-{width}x{height}-r{room}-s{seed}", _keep_largest_region(occ))


def trap_map(width: int, height: int, traps: int | None = None, seed: int = 0, name: str | None = None) -> GridMap:
    """Open field with U-shaped obstacles (random size and opening direction):
    the classic local-minimum trap for greedy goal seeking."""
    _check_size(width, height, 6)
    rng = np.random.default_rng(seed)
    n = traps if traps is not None else max(1, (width * height) // 64)
    occ = np.zeros((height, width), dtype=bool)
    for _ in range(n):
        uw = int(rng.integers(3, max(4, min(width, 8))))  # inner width + walls
        ud = int(rng.integers(3, max(4, min(height, 7))))
        u = np.zeros((ud, uw), dtype=bool)
        u[:, 0] = u[:, -1] = True
        u[-1, :] = True  # closed side at the bottom, opening at the top
        u = np.rot90(u, int(rng.integers(0, 4)))
        h, w = u.shape
        if h >= height or w >= width:
            continue
        r0 = int(rng.integers(1, height - h)) if height - h > 1 else 0
        c0 = int(rng.integers(1, width - w)) if width - w > 1 else 0
        occ[r0:r0 + h, c0:c0 + w] |= u
    return GridMap(name or f"trap-{width}x{height}-s{seed}", _keep_largest_region(occ))


def maze_map(width: int, height: int, loops: float = 0.1, seed: int = 0, name: str | None = None) -> GridMap:
    """Depth-first-backtracker maze with one-cell corridors; a fraction
    `loops` of the remaining inner walls is knocked out to create cycles."""
    _check_size(width, height, 3)
    rng = np.random.default_rng(seed)
    occ = np.ones((height, width), dtype=bool)
    ch, cw = (height + 1) // 2, (width + 1) // 2  # corridor cells at even coordinates
    seen = np.zeros((ch, cw), dtype=bool)
    stack = [(0, 0)]
    seen[0, 0] = True
    occ[0, 0] = False
    while stack:
        r, c = stack[-1]
        nbrs = [(r + dr, c + dc) for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1))
                if 0 <= r + dr < ch and 0 <= c + dc < cw and not seen[r + dr, c + dc]]
        if not nbrs:
            stack.pop()
            continue
        nr, nc = nbrs[int(rng.integers(len(nbrs)))]
        seen[nr, nc] = True
        occ[2 * nr, 2 * nc] = False
        occ[r + nr, c + nc] = False  # the wall between (2r,2c) and (2nr,2nc)
        stack.append((nr, nc))
    if loops > 0:
        walls = [(r, c) for r in range(height) for c in range(width)
                 if occ[r, c] and (r % 2) != (c % 2)]
        k = int(round(loops * len(walls)))
        for i in rng.permutation(len(walls))[:k]:
            occ[walls[i]] = False
    return GridMap(name or f"maze-{width}x{height}-s{seed}", _keep_largest_region(occ))


GENERATORS = {"random": random_map, "rooms": rooms_map, "trap": trap_map, "maze": maze_map}
