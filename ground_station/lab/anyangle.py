"""Any-angle shortest paths of a disc robot on an occupancy grid: the optimum
the sector policy's driven paths are measured against (`qnav study`).

The disc's centre must keep at least `radius` from every obstacle cell and
stay `radius` inside the map border (`ground_station.maps.planner.segment_clear`
tests a straight move exactly). A shortest path of the centre is made of
straight segments and arcs of radius `radius` around convex obstacle
corners. It is computed on a visibility graph: the nodes are the free cell
centres and, around every convex obstacle corner, the `arc_vertices`
vertices of the polygon circumscribed about the corner's quarter circle
(its edges touch the circle, so every edge keeps the clearance); two
nodes are joined when the straight segment between them keeps the
clearance (up to `TOL_MM`). Dijkstra from every goal. The polygon makes
each arc longer by the factor tan(d/2) / (d/2), d = 90 deg / arc_vertices
(1.3 % of the arc at 4 vertices, 0.3 % at 8); the straight parts are exact,
so the result is the true optimum up to that on the arcs (an upper bound up to the tolerance).

Not the 8-connected grid path (`octile_distances`), which is up to 8 %
longer than any-angle motion and ignores the robot's size.
"""

from __future__ import annotations

import math

import numpy as np

from ground_station.jitcache import numba
from ground_station.maps import GridMap
from ground_station.maps.planner import segment_clear

TOL_MM = 0.01  # clearance tolerance: the polygon's edges touch the arcs


def corner_vertices(occ: np.ndarray, cell: float, radius: float, arc_vertices: int = 4) -> np.ndarray:
    """(K, 2) world mm: the circumscribed-polygon vertices around every convex
    obstacle corner (a grid point with exactly one obstacle cell among its
    four, or two diagonal ones; off the map counts as obstacle)."""
    h, w = occ.shape
    pad = np.ones((h + 2, w + 2), dtype=bool)
    pad[1:-1, 1:-1] = occ.astype(bool)
    d = 0.5 * math.pi / arc_vertices
    rr = radius / math.cos(d / 2)
    out = []
    for gy in range(h + 1):  # grid point: column boundary gx, the row boundary above map row gy
        for gx in range(w + 1):
            # the four cells around it, keyed by their (dx, dy) side in world axes (y north);
            # map rows grow southward, pad is shifted by one
            quad = {(-1, 1): pad[gy, gx], (1, 1): pad[gy, gx + 1],
                    (-1, -1): pad[gy + 1, gx], (1, -1): pad[gy + 1, gx + 1]}
            occupied = [k for k, v in quad.items() if v]
            diagonal = len(occupied) == 2 and occupied[0][0] != occupied[1][0] and occupied[0][1] != occupied[1][1]
            if len(occupied) == 1 or diagonal:
                px, py = gx * cell, (h - gy) * cell
                for dx, dy in occupied:
                    # the rounded corner of this cell's inflation faces away from it: the
                    # quarter circle spans 45 deg either side of the direction (-dx, -dy)
                    base = math.atan2(-dy, -dx) - math.pi / 4
                    for j in range(arc_vertices):
                        a = base + (j + 0.5) * d
                        out.append((px + rr * math.cos(a), py + rr * math.sin(a)))
    return np.array(out, dtype=np.float64).reshape(-1, 2)


@numba.njit(cache=True)
def _visibility(occ, h, w, cell, a, b, r, same):
    """Length matrix between points a (n, 2) and b (m, 2): the distance where
    the segment keeps clearance r, else inf (same: a is b, fill symmetrically)."""
    n, m = a.shape[0], b.shape[0]
    out = np.full((n, m), np.inf)
    for i in range(n):
        j0 = i + 1 if same else 0
        for j in range(j0, m):
            if segment_clear(occ, h, w, cell, a[i, 0], a[i, 1], b[j, 0], b[j, 1], r):
                d = math.hypot(a[i, 0] - b[j, 0], a[i, 1] - b[j, 1])
                out[i, j] = d
                if same:
                    out[j, i] = d
    return out


@numba.njit(cache=True)
def _dijkstra_dense(wmat, src_edges):
    """Shortest distances to every node of the dense graph wmat (inf = no
    edge) from a source joined to node i by an edge of length src_edges[i]."""
    n = wmat.shape[0]
    dist = src_edges.copy()
    done = np.zeros(n, dtype=np.bool_)
    for _ in range(n):
        u = -1
        best = np.inf
        for i in range(n):
            if not done[i] and dist[i] < best:
                best = dist[i]
                u = i
        if u < 0:
            break
        done[u] = True
        for v in range(n):
            nd = best + wmat[u, v]
            if nd < dist[v]:
                dist[v] = nd
    return dist


def anyangle_distances(gridmap: GridMap, radius_mm: float, arc_vertices: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """(cells (n, 2) = (col, row) of the free cells, D (n, n) mm): the disc
    robot's any-angle shortest path length between the cell centres
    (inf: not connected for the disc)."""
    occ = np.ascontiguousarray(gridmap.occ, dtype=np.uint8)
    h, w = occ.shape
    cell = float(gridmap.cell_size_m) * 1000.0
    cells = np.array(gridmap.free_cells(), dtype=np.int64).reshape(-1, 2)
    centres = np.stack([(cells[:, 0] + 0.5) * cell, (h - cells[:, 1] - 0.5) * cell], axis=1).astype(np.float64)
    r = float(radius_mm) - TOL_MM
    verts = corner_vertices(occ, cell, float(radius_mm), arc_vertices)
    keep = np.array([segment_clear(occ, h, w, cell, x, y, x, y, r) for x, y in verts], dtype=bool)
    verts = np.ascontiguousarray(verts[keep]) if len(verts) else np.zeros((0, 2))
    vv = _visibility(occ, h, w, cell, verts, verts, r, True)
    cv = _visibility(occ, h, w, cell, centres, verts, r, False)  # centre -> vertex
    cc = _visibility(occ, h, w, cell, centres, centres, r, True)  # direct
    np.fill_diagonal(cc, 0.0)
    n = len(cells)
    out = cc.copy()
    for g in range(n):
        dv = _dijkstra_dense(vv, cv[g]) if len(verts) else np.zeros(0)
        via = (cv + dv[None, :]).min(axis=1) if len(verts) else np.full(n, np.inf)
        out[:, g] = np.minimum(out[:, g], via)
    return cells, np.minimum(out, out.T)
