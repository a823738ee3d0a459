"""Where `qnav bench nav` episodes fail: failure classes per controller (ground_station/nav/diagnose.py).

    python tools/nav_diagnose.py [--map NAME ...] [--episodes N] [--obstacles K] [--movers M] [--seed S]
                                 [--controllers learnt,seek,vfh,oracle,bug] [--json FILE]

Same seeded episodes as `qnav bench nav` (`nav.scenario.episodes(map, N, seed, K, M)`), rolled out one
period at a time in Python on the twin (slow: ~1-10 ms per period for the oracle), each outcome with its
class (collision: wall / disc / mover; loop or timeout: disc_ahead / near_disc / mover / other) and
whether a disc crosses a planned segment. Controllers: the shipped sector policy (`learnt`), the seek and
VFH tables, the privileged `oracle` (knows the discs; shortest path on the configuration space), and `bug`
(the hand-written Bug table on the robot's memory encoder: shipped go rows, sensors 0,1,2,6,7, block 150 mm,
leave 100 mm). Prints one line per map and controller and a summary; --json writes all of it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from firmware_py.encoders import BugMemory, MemorySectorEncoder  # noqa: E402
from firmware_py.policy import load_policy  # noqa: E402
from firmware_py.shipped_policies import resolve_policy_spec  # noqa: E402
from ground_station.bench.nav import DEFAULT_MAPS  # noqa: E402
from ground_station.learn.sector.twin import bearing_mrad  # noqa: E402
from ground_station.maps import load_map  # noqa: E402
from ground_station.nav import diagnose as dg  # noqa: E402
from ground_station.nav.controllers import policy_table, standard_controllers  # noqa: E402
from ground_station.nav.scenario import episodes  # noqa: E402

BUG = MemorySectorEncoder(15, (0, 1, 2, 6, 7), (100, 400), block_mm=150, leave_margin_mm=100)


def memory_act(enc: MemorySectorEncoder, q: np.ndarray) -> Callable[[dg.Obs], int]:
    """The robot's reference memory encoder (BugMemory reset per waypoint) on a table."""
    def act(o: dg.Obs) -> int:
        mem = o.memory.setdefault("bug", BugMemory())
        gx, gy = o.ep.waypoints[o.k]
        d = int(math.floor(math.hypot(gx - o.x, gy - o.y) + 0.5))
        s = enc.encode(mem, bearing_mrad(o.x, o.y, o.th, gx, gy), d, [int(v) for v in o.ranges],
                       [int(v) for v in o.status])
        a = int(np.argmax(q[s]))
        mem.note_action(a)
        return a
    return act


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--map", action="append", help="map (repeatable); default the bench's five")
    ap.add_argument("--episodes", type=int, default=100, help="episodes per map (default %(default)s)")
    ap.add_argument("--obstacles", type=int, default=3)
    ap.add_argument("--movers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--policy", default="policies:sector")
    ap.add_argument("--controllers", default="learnt,vfh,oracle")
    ap.add_argument("--json", help="write the rows and the summary here")
    args = ap.parse_args()
    pol = load_policy(str(resolve_policy_spec(args.policy)))
    tables = {c.name: c for c in standard_controllers(pol, ("learnt", "seek", "vfh"))}
    enc = tables["learnt"].encoder
    names = [c.strip() for c in args.controllers.split(",") if c.strip()]
    bad = [n for n in names if n not in ("learnt", "seek", "vfh", "oracle", "bug")]
    if bad:
        print(f"--controllers: unknown {', '.join(bad)}", file=sys.stderr)
        return 2
    bug_q = dg.hand_bug_table(policy_table(pol), pol.encoder, BUG) if "bug" in names else None  # type: ignore[arg-type]
    rows: dict[str, list[dict]] = {n: [] for n in names}
    for spec in args.map or DEFAULT_MAPS:
        gm = load_map(spec)
        eps = episodes(gm, args.episodes, args.seed, args.obstacles, args.movers)
        for name in names:
            act: Callable[[dg.Obs], int]
            if name == "oracle":
                act = dg.Oracle(gm)
            elif name == "bug":
                act = memory_act(BUG, bug_q)  # type: ignore[arg-type]
            else:
                act = dg.table_act(tables[name].q)
            got = [dg.rollout(e, gm, enc, act) for e in eps]  # type: ignore[arg-type]
            rows[name].extend(got)
            print(f"{gm.name:18s} {name:7s} success {sum(r['outcome'] == 'success' for r in got) / len(got):.3f} "
                  f"{dg.classify(got)}", flush=True)
    summary = {}
    for name, rr in rows.items():
        n = len(rr)
        blocked = [r for r in rr if r["blocked"]]
        free = [r for r in rr if not r["blocked"]]
        summary[name] = {
            "episodes": n,
            "success_rate": sum(r["outcome"] == "success" for r in rr) / n,
            "collision_rate": sum(r["outcome"] == "collision" for r in rr) / n,
            "classes": dg.classify(rr),
            "blocked_path_episodes": len(blocked),
            "success_blocked": sum(r["outcome"] == "success" for r in blocked) / max(1, len(blocked)),
            "success_unblocked": sum(r["outcome"] == "success" for r in free) / max(1, len(free)),
        }
        s = summary[name]
        print(f"ALL {name:7s} success {s['success_rate']:.3f} collision {s['collision_rate']:.3f} "
              f"| path crossed by a disc: {s['blocked_path_episodes']}/{n} episodes, success there "
              f"{s['success_blocked']:.3f}, elsewhere {s['success_unblocked']:.3f} | {s['classes']}")
    if args.json:
        Path(args.json).write_text(json.dumps({"scenario": {"maps": list(args.map or DEFAULT_MAPS),
                                                            "episodes_per_map": args.episodes,
                                                            "obstacles": args.obstacles, "movers": args.movers,
                                                            "seed": args.seed},
                                               "summary": summary, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
