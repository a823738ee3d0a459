"""What a space-time search over the robot's own motions costs in pure Python (issue 47's next step).

The seeing oracle (docs/results.md 6.1) plans where to be when among the movers, with instant turns and
sideways steps; the robot needs that search over its own motions, in its planner worker (stdlib, no
numpy). This measures the search, not a controller: A* over (x, y, heading in 45-degree steps, t) on a
raster of RASTER mm of the map's free space (walls grown by the robot's 160 mm radius), one step of
RASTER / 400 mm/s (the robot's forward speed); each step waits, drives one cell ahead or turns 45
degrees in place. Three movers (250 mm radius) walk their shortest route between two random free
cells at 300-600 mm/s, known exactly (a tracker's best case). The heuristic is the static route length
(Dijkstra from the goal, which the planner has). Queries: start and goal 2-4 m apart along the route,
seeded; CPU per search (time.process_time) and nodes expanded, for all searches and for those that find
a path (the others end when the horizon is spent).

    .venv/bin/python tools/spacetime_cost.py maze-12x12-s306 maze-16x16-s304 --searches 40
"""

from __future__ import annotations

import argparse
import heapq
import math
import random
import time

from ground_station.maps import load_map

ROBOT_R_MM, MOVER_R_MM, FORWARD_MM_S = 160, 250, 400.0
DIRS = [(1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1)]
Cell = tuple[int, int]


class Space:
    """The map's free space on a raster (walls grown by the robot's radius)."""

    def __init__(self, name: str, raster_mm: int) -> None:
        gm = load_map(name)
        n = max(1, round(gm.cell_size_m * 1000) // raster_mm)
        self.raster_mm = raster_mm
        self.h, self.w = gm.occ.shape[0] * n, gm.occ.shape[1] * n
        free = [[not gm.occ[y // n][x // n] for x in range(self.w)] for y in range(self.h)]
        g = math.ceil(ROBOT_R_MM / raster_mm)
        self.free = [[all(free[yy][xx] for yy in range(max(0, y - g), min(self.h, y + g + 1))
                          for xx in range(max(0, x - g), min(self.w, x + g + 1)))
                      for x in range(self.w)] for y in range(self.h)]
        self.cells = [(x, y) for y in range(self.h) for x in range(self.w) if self.free[y][x]]

    def ok(self, x: int, y: int) -> bool:
        return 0 <= x < self.w and 0 <= y < self.h and self.free[y][x]

    def dijkstra(self, goal: Cell) -> tuple[dict[Cell, float], dict[Cell, Cell]]:
        """Route length (cells) to `goal` from every reachable cell, and each cell's next cell."""
        dist, nxt = {goal: 0.0}, {}
        pq = [(0.0, goal)]
        while pq:
            c, (x, y) = heapq.heappop(pq)
            if c > dist[(x, y)]:
                continue
            for dx, dy in DIRS:
                nx, ny = x + dx, y + dy
                if self.ok(nx, ny):
                    nc = c + (1.4142 if dx and dy else 1.0)
                    if nc < dist.get((nx, ny), 1e18):
                        dist[(nx, ny)], nxt[(nx, ny)] = nc, (x, y)
                        heapq.heappush(pq, (nc, (nx, ny)))
        return dist, nxt

    def walk(self, a: Cell, b: Cell, speed_mm_s: float, dt_s: float, steps: int) -> list[tuple[float, float]] | None:
        """A mover's centre (raster cells) at each step, walking a's shortest route to b, then standing."""
        _, nxt = self.dijkstra(b)
        if a != b and a not in nxt:
            return None
        path = [a]
        while path[-1] != b:
            path.append(nxt[path[-1]])
        cum = [0.0]
        for p, q in zip(path, path[1:], strict=False):
            cum.append(cum[-1] + math.dist(p, q))
        out, j = [], 0
        for k in range(steps + 2):
            s = min(k * speed_mm_s * dt_s / self.raster_mm, cum[-1])
            while j < len(path) - 2 and cum[j + 1] < s:
                j += 1
            if len(path) == 1:
                out.append((float(a[0]), float(a[1])))
                continue
            (px, py), (qx, qy) = path[j], path[j + 1]
            f = (s - cum[j]) / ((cum[j + 1] - cum[j]) or 1.0)
            out.append((px + (qx - px) * f, py + (qy - py) * f))
        return out


def search(space: Space, start: Cell, goal: Cell, movers: list[list[tuple[float, float]]],
           to_goal: dict[Cell, float], steps: int) -> tuple[int | None, int]:
    """A* over (x, y, heading, t): (steps to the goal or None, nodes expanded)."""
    reach2 = ((MOVER_R_MM + ROBOT_R_MM) / space.raster_mm) ** 2

    def hit(x: int, y: int, t: int) -> bool:
        return any((x - m[t][0]) ** 2 + (y - m[t][1]) ** 2 < reach2 for m in movers)

    first = (start[0], start[1], 0, 0)
    pq = [(to_goal[start], 0, first)]
    seen = {first}
    expanded = 0
    while pq:
        _, g, (x, y, hd, t) = heapq.heappop(pq)
        expanded += 1
        if (x, y) == goal:
            return g, expanded
        if t >= steps:
            continue
        dx, dy = DIRS[hd]
        for nx, ny, nh in ((x, y, hd), (x + dx, y + dy, hd), (x, y, (hd + 1) % 8), (x, y, (hd - 1) % 8)):
            key = (nx, ny, nh, t + 1)
            if key in seen or not space.ok(nx, ny) or hit(nx, ny, t + 1):
                continue
            seen.add(key)
            h = to_goal.get((nx, ny))
            if h is not None:
                heapq.heappush(pq, (g + 1 + h, g + 1, key))
    return None, expanded


def measure(name: str, raster_mm: int, horizon_s: float, searches: int, seed: int) -> str:
    space = Space(name, raster_mm)
    dt_s = raster_mm / FORWARD_MM_S
    steps = int(horizon_s / dt_s)
    rng = random.Random(seed)
    cpu: list[float] = []
    nodes: list[int] = []
    found_cpu: list[float] = []
    found_nodes: list[int] = []
    while len(cpu) < searches:
        start, goal = rng.choice(space.cells), rng.choice(space.cells)
        to_goal, _ = space.dijkstra(goal)
        if not 2000 / raster_mm <= to_goal.get(start, 0.0) <= 4000 / raster_mm:
            continue
        movers: list[list[tuple[float, float]]] = []
        while len(movers) < 3:
            a, b = rng.choice(space.cells), rng.choice(space.cells)
            walk = space.walk(a, b, rng.uniform(300, 600), dt_s, steps)
            if walk is not None and math.dist(a, start) * raster_mm >= 800:
                movers.append(walk)
        t0 = time.process_time()
        got, expanded = search(space, start, goal, movers, to_goal, steps)
        spent = time.process_time() - t0
        cpu.append(spent)
        nodes.append(expanded)
        if got is not None:
            found_cpu.append(spent)
            found_nodes.append(expanded)
    cpu.sort()
    nodes.sort()
    k = len(cpu)
    found = (f"{max(found_nodes)} nodes, {max(found_cpu) * 1e3:.0f} ms" if found_cpu else "-")
    return (f"| {name} | {k} | {len(found_cpu)} | {cpu[k // 2] * 1e3:.0f} | {cpu[int(k * 0.9)] * 1e3:.0f} | "
            f"{cpu[-1] * 1e3:.0f} | {nodes[k // 2]} | {nodes[-1]} | {found} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("maps", nargs="+", help="built-in map names or .map files")
    p.add_argument("--raster", type=int, default=100, metavar="MM", help="raster cell (default %(default)s mm)")
    p.add_argument("--horizon", type=float, default=15.0, metavar="S", help="search horizon (default %(default)s s)")
    p.add_argument("--searches", type=int, default=40, help="queries per map (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="query seed (default %(default)s)")
    args = p.parse_args()
    if args.raster <= 0 or args.horizon <= 0 or args.searches <= 0:
        p.error("--raster, --horizon and --searches must be positive")
    for name in args.maps:
        try:
            load_map(name)
        except (ValueError, OSError) as exc:
            p.error(f"map {name!r}: {exc}")
    print(f"raster {args.raster} mm, step {args.raster / FORWARD_MM_S:.2f} s, horizon {args.horizon:g} s, "
          f"3 movers, routes 2-4 m, seed {args.seed}; CPU in ms")
    print("| map | searches | found | CPU median | p90 | max | nodes median | max | worst found |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for name in args.maps:
        print(measure(name, args.raster, args.horizon, args.searches, args.seed), flush=True)


if __name__ == "__main__":
    main()
