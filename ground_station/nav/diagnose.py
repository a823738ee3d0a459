"""Where navigation episodes fail: per-episode failure classes and a privileged oracle.

A Python-loop rollout on the twin with obstacles (the jitted
`learn.sector.obstacles.obs_period_step`, so the physics, sensing and
waypoint advance are the bench's), driven by any `act(obs) -> action`
function, that records what the bench's kernel does not:

* collisions by what was touched: `wall` (an obstacle cell or the border),
  `disc` (a static unmapped disc) or `mover`;
* loops/timeouts by where the robot was stuck: `disc_ahead` (the straight
  line from the robot to its current waypoint passes through a static disc
  grown by the robot's radius: the reactive "go round it" case),
  `near_disc` (within 300 mm of a disc surface, line clear), `mover`
  (a mover within 300 mm) or `other` (walls, dithers);
* per episode, whether a planned segment crosses a disc at all (`blocked`).

`oracle_act` is a privileged controller (it knows the discs and the
movers' positions): it steers along the shortest path on the scenario's own
configuration-space raster with the discs (`nav.scenario._cspace`, robot
radius + 75 mm, as the detourable check), turning in place when the look-ahead point is more than
0.35 rad off and waiting (turning) when driving forward would touch a
mover. It tests whether the episodes are solvable with the robot's actions,
independent of sensing.

`hand_bug_table` builds a `MemorySectorEncoder` table (the robot's Bug
memory: mode + side held per waypoint + previous turn) whose go rows are a
sector table and whose wall rows are hand-written wall following: what a
detour memory with fixed rules buys on the robot's own sensing.
"""

from __future__ import annotations

import heapq
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from firmware_py import robot_spec
from firmware_py.encoders import MemorySectorEncoder, SectorEncoder
from ground_station.learn.sector.obstacles import (
    hits_discs,
    obs_period_step,
    sense_obs,
    stall_check,
)
from ground_station.learn.sector.twin import (
    RADIUS_MM,
    bearing_mrad,
    disc_hits,
    encode_fast,
    encoder_arrays,
)
from ground_station.maps import GridMap
from ground_station.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS
from ground_station.nav.scenario import RASTER_MM, Episode, _cspace, rollout_arrays

FORWARD, LEFT, RIGHT, REVERSE = range(4)
FWD_MM = 400.0 * robot_spec.CONTROL_PERIOD_US / 1e6


@dataclass
class Obs:
    """What a controller may look at in one period (privileged fields included)."""

    x: float
    y: float
    th: float
    k: int
    ranges: np.ndarray
    status: np.ndarray
    state: int
    ep: Episode
    movers: np.ndarray
    memory: dict = field(default_factory=dict)


def _seg_hits_disc(ax: float, ay: float, bx: float, by: float, cx: float, cy: float, r: float) -> bool:
    dx, dy = bx - ax, by - ay
    l2 = dx * dx + dy * dy
    t = 0.0 if l2 == 0 else max(0.0, min(1.0, ((cx - ax) * dx + (cy - ay) * dy) / l2))
    return math.hypot(ax + t * dx - cx, ay + t * dy - cy) < r


def blocked_segments(ep: Episode) -> int:
    """Planned segments (start -> waypoints) that a disc grown by the robot's radius crosses."""
    pts = [ep.start[:2], *ep.waypoints]
    return sum(any(_seg_hits_disc(*a, *b, cx, cy, r + RADIUS_MM) for cx, cy, r in ep.discs)
               for a, b in zip(pts[:-1], pts[1:], strict=True))


def rollout(ep: Episode, gm: GridMap, encoder: SectorEncoder, act: Callable[[Obs], int]) -> dict:
    """One episode as the bench runs it (budget, loop rule), with failure details."""
    occ = np.ascontiguousarray(gm.occ, dtype=np.uint8)
    h, w = occ.shape
    c = gm.cell_size_m * 1000.0
    sectors, sensors, edges, _which = encoder_arrays(encoder)
    which = np.ones(robot_spec.SENSOR_COUNT, dtype=np.bool_)  # all sensors (the oracle may look)
    discs, movers, wps, rem, plan_len = rollout_arrays(ep)
    x, y, th = ep.start
    budget = int(BUDGET_BASE + BUDGET_FACTOR * plan_len / FWD_MM)
    ranges = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
    status = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
    rw = np.zeros(7)
    k = 0
    phi = math.hypot(x - wps[0, 0], y - wps[0, 1]) + rem[0]
    best, since = phi, 0
    sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, movers)
    s = encode_fast(bearing_mrad(x, y, th, wps[0, 0], wps[0, 1]), ranges, status, sectors, sensors, edges)
    memory: dict = {}
    outcome, detail = "timeout", ""
    t = 0
    while t < budget:
        k_before = k
        o = Obs(x, y, th, k, ranges.copy(), status.copy(), s, ep, movers, memory)
        a = act(o)
        x, y, th, phi, _, s, hit, success, _, k = obs_period_step(
            occ, h, w, c, x, y, th, phi, wps, rem, len(wps), k, a, rw, which, ranges, status,
            sectors, sensors, edges, discs, movers, 0.0)
        if k != k_before:
            memory.clear()
        t += 1
        if hit:
            outcome = "collision"
            if disc_hits(occ, h, w, c, x, y, RADIUS_MM):
                detail = "wall"
            elif hits_discs(x, y, RADIUS_MM, discs, np.zeros((0, 5))):
                detail = "disc"
            else:
                detail = "mover"
            break
        if success:
            outcome = "success"
            break
        best, since, stalled = stall_check(phi, best, since, STALL_STEPS)
        if stalled:
            outcome = "loop"
            break
    if outcome in ("loop", "timeout"):
        gx, gy = wps[k]
        if any(_seg_hits_disc(x, y, gx, gy, cx, cy, r + RADIUS_MM) for cx, cy, r in discs):
            detail = "disc_ahead"
        elif any(math.hypot(x - cx, y - cy) - r - RADIUS_MM < 300 for cx, cy, r in discs):
            detail = "near_disc"
        elif any(math.hypot(x - m[0], y - m[1]) - m[4] - RADIUS_MM < 300 for m in movers):
            detail = "mover"
        else:
            detail = "other"
    return {"outcome": outcome, "detail": detail, "steps": t, "discs": len(ep.discs),
            "blocked": blocked_segments(ep), "map": ep.map}


def classify(rows: list[dict]) -> dict[str, int]:
    return dict(sorted(Counter(f"{r['outcome']}:{r['detail']}" if r["detail"] else r["outcome"]
                               for r in rows).items()))


# --- controllers -------------------------------------------------------------------

def table_act(q: np.ndarray) -> Callable[[Obs], int]:
    """Greedy on a table over the encoder state (ties to the lowest index, as the robot)."""
    return lambda o: int(np.argmax(q[o.state]))


class Oracle:
    """Privileged shortest-path follower on the configuration-space raster with the discs."""

    def __init__(self, gm: GridMap, clear_mm: float = RADIUS_MM + 75.0) -> None:
        self.gm = gm
        self.clear = clear_mm
        self.tol = 0.1  # rad: a turn period turns ~0.065 rad
        self._cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def _field(self, o: Obs) -> tuple[np.ndarray, np.ndarray]:
        key = (id(o.ep), o.k)
        if key not in self._cache:
            gm = self.gm
            occ = np.ascontiguousarray(gm.occ, dtype=np.uint8)
            c = gm.cell_size_m * 1000.0
            free = _cspace(occ, c, np.asarray(o.ep.discs, dtype=np.float64).reshape(-1, 3), RASTER_MM, self.clear)
            gx, gy = o.ep.waypoints[o.k]
            self._cache[key] = (free, _dijkstra(free, int(gx // RASTER_MM), int(gy // RASTER_MM)))
        return self._cache[key]

    def __call__(self, o: Obs) -> int:
        free, dist = self._field(o)
        ny, nx = free.shape
        ix, iy = min(nx - 1, int(o.x // RASTER_MM)), min(ny - 1, int(o.y // RASTER_MM))
        tx, ty = o.ep.waypoints[o.k]
        if math.hypot(tx - o.x, ty - o.y) < 250:
            px, py = tx, ty  # close: aim at the waypoint itself
        else:
            # the reachable raster point within 2 steps of the robot, then ~150 mm down the field
            near = [(dist[yy, xx] + 0.5 * math.hypot(xx - ix, yy - iy), xx, yy)
                    for yy in range(max(0, iy - 2), min(ny, iy + 3)) for xx in range(max(0, ix - 2), min(nx, ix + 3))
                    if math.isfinite(dist[yy, xx])]
            if not near:
                px, py = tx, ty
            else:
                _, cx, cy = min(near)
                for _ in range(3):
                    d, bx, by = min((dist[yy, xx], xx, yy) for yy in range(max(0, cy - 1), min(ny, cy + 2))
                                    for xx in range(max(0, cx - 1), min(nx, cx + 2)))
                    if d >= dist[cy, cx]:
                        break
                    cx, cy = bx, by
                px, py = (cx + 0.5) * RASTER_MM, (cy + 0.5) * RASTER_MM
        err = math.remainder(math.atan2(py - o.y, px - o.x) - o.th, 2 * math.pi)
        if abs(err) > self.tol:
            return LEFT if err > 0 else RIGHT
        nx_, ny_ = o.x + FWD_MM * math.cos(o.th), o.y + FWD_MM * math.sin(o.th)
        if hits_discs(nx_, ny_, RADIUS_MM + 5.0, np.zeros((0, 3)), o.movers):
            return LEFT if err >= 0 else RIGHT  # let the mover pass (turning in place touches nothing)
        return FORWARD


def _dijkstra(free: np.ndarray, gx: int, gy: int) -> np.ndarray:
    ny, nx = free.shape
    dist = np.full((ny, nx), np.inf)
    gx, gy = min(nx - 1, max(0, gx)), min(ny - 1, max(0, gy))
    dist[gy, gx] = 0.0
    heap = [(0.0, gy, gx)]
    while heap:
        d, y, x = heapq.heappop(heap)
        if d > dist[y, x]:
            continue
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                yy, xx = y + dy, x + dx
                if (dy or dx) and 0 <= yy < ny and 0 <= xx < nx and free[yy, xx]:
                    if dy and dx and not (free[y + dy, x] and free[y, x + dx]):
                        continue
                    nd = d + (1.4142 if dy and dx else 1.0)
                    if nd < dist[yy, xx]:
                        dist[yy, xx] = nd
                        heapq.heappush(heap, (nd, yy, xx))
    return dist


def go_rows_table(go_q: np.ndarray, go_encoder: SectorEncoder, encoder: MemorySectorEncoder) -> np.ndarray:
    """A `MemorySectorEncoder` table whose go rows (every previous turn) are
    `go_q`, a table over `go_encoder` (same sectors and range edges, its
    sensors among the memory encoder's; the others are ignored); wall rows 0."""
    if encoder.bearing_sectors != go_encoder.bearing_sectors or encoder.range_edges_mm != go_encoder.range_edges_mm:
        raise ValueError("the go table's encoder must have the memory encoder's sectors and range edges")
    sens = list(encoder.sensors)
    if not set(go_encoder.sensors) <= set(sens):
        raise ValueError("the go table's sensors must be among the memory encoder's")
    nb = encoder.base.nbins
    r_states = encoder.range_states
    gper = go_encoder.nbins ** len(go_encoder.sensors)
    q = np.zeros((encoder.n_states, encoder.n_actions))
    for rs in range(r_states):
        bins = {s: (rs // nb ** j) % nb for j, s in enumerate(sens)}
        g = sum(bins[s] * nb ** j for j, s in enumerate(go_encoder.sensors))
        for turn in range(3):
            off = turn * encoder.mode_states
            for b in range(encoder.bearing_sectors):
                q[off + b * r_states + rs] = go_q[b * gper + g]
    return q


def hand_bug_table(go_q: np.ndarray, go_encoder: SectorEncoder, encoder: MemorySectorEncoder) -> np.ndarray:
    """`go_rows_table` plus hand-written Bug wall following in the wall rows,
    on the followed side's diagonal and side sensors (1, 2 or 7, 6): front
    or either of them in the first bin -> turn away; both beyond the last
    edge (the wall is lost) -> forward right after a turn away, else turn
    toward it; otherwise forward. What a memory with fixed rules gives on
    the robot's sensing, for the diagnosis (docs/training.md)."""
    sens = list(encoder.sensors)
    if not {0, 1, 2, 6, 7} <= set(sens):
        raise ValueError("hand_bug_table needs sensors 0, 1, 2, 6, 7")
    q = go_rows_table(go_q, go_encoder, encoder)
    nb = encoder.base.nbins
    r_states = encoder.range_states
    for rs in range(r_states):
        bins = {s: (rs // nb ** j) % nb for j, s in enumerate(sens)}
        for turn in range(3):
            off = turn * encoder.mode_states
            for mode, (diag, side, away, toward) in ((1, (7, 6, LEFT, RIGHT)), (2, (1, 2, RIGHT, LEFT))):
                if bins[0] < nb - 1 or bins[diag] == 0 or bins[side] == 0:
                    a = away
                elif bins[diag] == nb - 1 and bins[side] == nb - 1:
                    a = FORWARD if turn == away else toward  # TURN_LEFT/RIGHT == the action's index
                else:
                    a = FORWARD
                q[off + (encoder.bearing_sectors + mode - 1) * r_states + rs, a] = 1.0
    return q
