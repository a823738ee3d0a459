"""Issue 47 experiment: what closes the way at each whole-map "no route" of a blocked-passage episode.

Runs one episode of `qnav bench decisions --blocked both` (the same seeded episodes: the map's
`blocked_both`, 2 yielding movers, seed 0) with the learnt controller on the twin, and at every
whole-map search that found no route (at most one a second) prints the robot's pose, the waypoint,
and where the obstacle memory's points lie: on the blocked disc (within `NEAR_MM` of its surface; the farthest outside it:
a range beam's cone places a return on its axis, off the body), on a mover (within `NEAR_MM` of a
mover's body now), or elsewhere; with the movers' travel over the last 10 s. `--draw PNG` draws the
map, the disc, the points and the movers at the first, middle and last of those searches.

    .venv/bin/python tools/no_route_memory.py random-12x12-s309 14 --draw /tmp/ep.png
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

NEAR_MM = 100.0
TRAVEL_PERIODS = 200  # 10 s at the 20 Hz control period


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("map", help="built-in map name or a .map file")
    p.add_argument("index", type=int, help="the episode's index on that map (as in bench ceiling's JSON)")
    p.add_argument("--episodes", type=int, default=20, help="episodes per map of the bench (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="scenario seed (default %(default)s)")
    p.add_argument("--draw", type=Path, metavar="PNG", help="draw the memory at the first, middle, last search")
    args = p.parse_args()
    if not 0 <= args.index < args.episodes:
        p.error(f"index {args.index}: expected 0..{args.episodes - 1}")

    from firmware_py.kinds.sector.recoveries import GLOBAL
    from firmware_py.policy import load_policy
    from firmware_py.shipped_policies import resolve_policy_spec
    from ground_station.lab.nav import decisions, planned
    from ground_station.lab.nav.controllers import standard_controllers
    from ground_station.lab.nav.scenario import MOVER_SPEED_MM_S, MoverStyle, blocked_both
    from ground_station.maps import load_map

    gm = load_map(args.map)
    ep = blocked_both(gm, args.episodes, args.seed, 0, 2, MoverStyle(speed=MOVER_SPEED_MM_S, yields=True))[args.index]
    dx, dy, dr = ep.blocked["disc"]
    print(f"{args.map} episode {args.index}: blocked disc ({dx:.0f}, {dy:.0f}) r {dr:.0f}, "
          f"{'a detour exists' if ep.blocked['detour'] else 'no detour'}")
    movers_at: list[Any] = []
    lines: list[str] = []  # one per whole-map search that found no route
    asked_us = [0]
    snaps: list[tuple[float, float, float, tuple[int, int], list[tuple[int, int]], Any]] = []
    real_rollout = planned.rollout

    def rollout(*a: Any, **k: Any) -> Any:  # decisions.trace's rollout, its watch also noting the movers
        watch = k.pop("watch", None)

        def seen(x: float, y: float, movers: Any) -> None:
            movers_at.append(movers[:, [0, 1, 4]].copy())
            if watch is not None:
                watch(x, y, movers)
        k["watch"] = seen
        return real_rollout(*a, **k)

    real_recovering = decisions.TracingTarget._recovering

    def recovering(self: Any, now_us: int, x: float, y: float, waypoint: tuple[int, int], ans: Any,
                   memory: Any) -> Any:
        if ans is not None and ans.no_route and self.mode == GLOBAL and movers_at and now_us >= asked_us[0]:
            asked_us[0] = now_us + 1_000_000  # at most one a second (approaching what came in, it asks each tick)
            pts = [(px, py) for px, py, _ in memory.points.values()]
            snaps.append((now_us / 1e6, x, y, waypoint, pts, movers_at[-1]))
            on_disc = [math.hypot(px - dx, py - dy) - dr for px, py in pts
                       if math.hypot(px - dx, py - dy) - dr <= NEAR_MM]
            on_mover = sum(any(math.hypot(px - mx, py - my) - mr <= NEAR_MM for mx, my, mr in movers_at[-1].tolist())
                           for px, py in pts)
            before = movers_at[max(0, len(movers_at) - TRAVEL_PERIODS)]
            travel = [round(math.hypot(a[0] - b[0], a[1] - b[1])) for a, b in zip(movers_at[-1].tolist(),
                                                                                    before.tolist(), strict=True)]
            near = [round(math.hypot(mx - x, my - y) - mr) for mx, my, mr in movers_at[-1].tolist()]
            lines.append(f"t={now_us / 1e6:5.1f} s robot ({x:.0f}, {y:.0f}) waypoint {waypoint}: {len(pts)} points, "
                  f"{len(on_disc)} on the disc (farthest {max(on_disc, default=0):.0f} mm outside it), "
                  f"{on_mover} on a mover, {len(pts) - len(on_disc) - on_mover} elsewhere; movers' bodies "
                  f"{near} mm from the robot's centre, moved {travel} mm in the last 10 s")
        return real_recovering(self, now_us, x, y, waypoint, ans, memory)

    planned.rollout = rollout
    setattr(decisions.TracingTarget, "_recovering", recovering)  # noqa: B010 - a method replaced, for this run
    (ctrl,) = standard_controllers(load_policy(str(resolve_policy_spec("policies:sector"))), ("learnt",))
    row = decisions.trace([ep], {gm.name: gm}, ctrl)[0]
    shown = lines if len(lines) <= 6 else [*lines[:3], f"... {len(lines) - 6} more ...", *lines[-3:]]
    print("\n".join(shown))
    print(f"outcome {row['outcome']} ({row['decision']}) after {row['periods'] / 20:.1f} s")
    if args.draw is not None and snaps:
        _draw(args.draw, gm, ep, snaps)


def _draw(path: Path, gm: Any, ep: Any, snaps: list) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = gm.cell_size_m * 1000.0
    picks = [snaps[0], snaps[len(snaps) // 2], snaps[-1]][:len(snaps)]
    fig, axes = plt.subplots(1, len(picks), figsize=(6 * len(picks), 6), squeeze=False)
    for ax, (t, x, y, wp, pts, movers) in zip(axes[0], picks, strict=True):
        ax.imshow(gm.occ, cmap="Greys", extent=(0, gm.width * c, 0, gm.height * c), origin="upper")
        bx, by, br = ep.blocked["disc"]
        ax.add_patch(plt.Circle((bx, by), br, color="brown", alpha=0.5))
        for mx, my, mr in movers.tolist():
            ax.add_patch(plt.Circle((mx, my), mr, color="orange", alpha=0.6))
        ax.scatter([q[0] for q in pts], [q[1] for q in pts], s=5, c="red")
        ax.plot([x], [y], "bo")
        ax.plot([wp[0]], [wp[1]], "g+", ms=12)
        ax.set_title(f"no route at {t:.1f} s: {len(pts)} points (red), movers orange")
    fig.savefig(path, dpi=70)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
