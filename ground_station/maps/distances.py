"""Shortest distances to one goal cell, jitted.

* `bfs_distances`: 4-connected steps (the cell encoding's moves).
* `octile_distances`: 8-connected, diagonal cost sqrt(2), no corner cutting
  (a diagonal move needs both orthogonal neighbours free): the reference for
  the sector encoding's path lengths.

Both return arrays indexed [row, col] and accept a goal on an obstacle
(everything is then unreachable).
"""

from __future__ import annotations

import heapq
import math

import numpy as np

from ground_station.jitcache import numba

_DC4 = np.array([0, 0, -1, 1], dtype=np.int64)
_DR4 = np.array([-1, 1, 0, 0], dtype=np.int64)


@numba.njit(cache=True)
def _bfs(occ, gc, gr, dc, dr):
    h, w = occ.shape
    dist = np.full((h, w), -1, dtype=np.int32)
    if occ[gr, gc]:
        return dist
    queue = np.empty(h * w, dtype=np.int64)
    head = 0
    tail = 0
    dist[gr, gc] = 0
    queue[tail] = gr * w + gc
    tail += 1
    while head < tail:
        cur = queue[head]
        head += 1
        r = cur // w
        c = cur % w
        d = dist[r, c] + 1
        for k in range(4):
            nr = r + dr[k]
            nc = c + dc[k]
            if 0 <= nr < h and 0 <= nc < w and not occ[nr, nc] and dist[nr, nc] < 0:
                dist[nr, nc] = d
                queue[tail] = nr * w + nc
                tail += 1
    return dist


@numba.njit(cache=True)
def octile_moves(occ, h: int, w: int, r: int, c: int, out) -> int:
    """The 8-connected moves from (r, c) onto free cells as (row, col, cost) rows into `out` (8, 3),
    in a fixed order; returns their count."""
    n = 0
    for dr in range(-1, 2):
        for dc in range(-1, 2):
            nr = r + dr
            nc = c + dc
            if (dr == 0 and dc == 0) or not (0 <= nr < h and 0 <= nc < w) or occ[nr, nc]:
                continue
            diagonal = dr != 0 and dc != 0
            if diagonal and (occ[r + dr, c] or occ[r, c + dc]):
                continue
            out[n, 0] = nr
            out[n, 1] = nc
            out[n, 2] = math.sqrt(2.0) if diagonal else 1.0
            n += 1
    return n


@numba.njit(cache=True)
def _octile(occ, gc, gr):
    h, w = occ.shape
    dist = np.full((h, w), np.inf)
    if occ[gr, gc]:
        return dist
    done = np.zeros((h, w), dtype=np.bool_)
    moves = np.empty((8, 3))
    dist[gr, gc] = 0.0
    heap = [(0.0, gr * w + gc)]
    while len(heap) > 0:
        d, cur = heapq.heappop(heap)
        r = cur // w
        c = cur % w
        if done[r, c]:
            continue
        done[r, c] = True
        for k in range(octile_moves(occ, h, w, r, c, moves)):
            nr = int(moves[k, 0])
            nc = int(moves[k, 1])
            nd = d + moves[k, 2]
            if nd < dist[nr, nc]:
                dist[nr, nc] = nd
                heapq.heappush(heap, (nd, nr * w + nc))
    return dist


def _check(occ: np.ndarray, goal_col: int, goal_row: int) -> np.ndarray:
    occ = np.ascontiguousarray(np.asarray(occ, dtype=np.bool_))
    if occ.ndim != 2:
        raise ValueError(f"occupancy must be 2-D, got shape {occ.shape}")
    h, w = occ.shape
    if not (0 <= goal_col < w and 0 <= goal_row < h):
        raise ValueError(f"goal ({goal_col},{goal_row}) outside the {w}x{h} map")
    return occ


def bfs_distances(occ: np.ndarray, goal_col: int, goal_row: int) -> np.ndarray:
    """4-connected step counts to the goal, int32 (H, W), -1 unreachable."""
    occ = _check(occ, goal_col, goal_row)
    return _bfs(occ, int(goal_col), int(goal_row), _DC4, _DR4)


def octile_distances(occ: np.ndarray, goal_col: int, goal_row: int) -> np.ndarray:
    """8-connected distances (diagonal sqrt 2, no corner cutting), float64 (H, W), inf unreachable."""
    occ = _check(occ, goal_col, goal_row)
    return _octile(occ, int(goal_col), int(goal_row))
