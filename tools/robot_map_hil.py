"""The shipped sector-memory table in the direct setting, lockstep HIL, with and without the robot's own map.

Issue 32: the .qtab carries the map it was trained on (paper10); on another world the robot must
localise and plan on that world's map (`qnav map upload`; `policy.on_robot_map`). N seeded episodes
(start and goal free cells at least 6 BFS steps apart, random heading, 120 s of sim each) on MAP, the
robot given the map the plant plays (`--map robot`, the default) or left with the policy's (`--map
policy`); prints goals reached without a bumper contact and the episodes with one.

    .venv/bin/python tools/robot_map_hil.py rooms-16x16-s1 --episodes 50 --plant realistic
"""

from __future__ import annotations

import argparse
import math
import random
import time

from firmware_py import robot_spec
from firmware_py.policy import load_policy
from firmware_py.shipped_policies import shipped_policy
from ground_station.lab.rigs.lockstep import LockstepRig
from ground_station.maps import bfs_distances, load_map
from sim_bridge.profiles import profile


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("world", help="the map the plant plays (built-in name or .map file)")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--map", choices=("robot", "policy"), default="robot",
                   help="robot: the robot is given the plant's map; policy: it keeps the one in the .qtab")
    p.add_argument("--plant", choices=("ideal", "realistic"), default=None, help="plant profile (default: the sim's)")
    args = p.parse_args()
    gm = load_map(args.world)
    pol = load_policy(shipped_policy("sector_memory"))
    plant = profile(args.plant) if args.plant else None
    rng = random.Random(0)
    free = [(c, r) for r in range(gm.height) for c in range(gm.width) if not gm.occ[r, c]]
    ok = bumped = 0
    t0 = time.monotonic()
    for ep in range(args.episodes):
        while True:
            s, g = rng.choice(free), rng.choice(free)
            if bfs_distances(gm.occ, *g)[s[1], s[0]] >= 6:
                break
        sx, sy = robot_spec.cell_center_mm(*s, gm.height)
        goal = robot_spec.cell_center_mm(*g, gm.height)
        start = (sx / 1000, sy / 1000, rng.uniform(-math.pi, math.pi))
        with LockstepRig(gm.occ, pol, start, [goal], seed=ep, profile=plant, robot_map=args.map == "robot") as rig:
            while rig.plant.time_us < 120_000_000 and not rig.runner.done.is_set():
                rig.tick()
            bump = any("bumper" in t.cause for t in rig.ctrl.transitions)
            ok += rig.runner.result == "reached" and not bump
            bumped += bump
    print(f"{gm.name}, {args.map}'s map, plant {args.plant or 'default'}: {ok}/{args.episodes} reached, "
          f"{bumped} with a bumper contact ({time.monotonic() - t0:.1f} s wall)")


if __name__ == "__main__":
    main()
