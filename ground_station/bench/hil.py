"""`qnav bench hil`: lockstep hardware-in-the-loop episodes, in one process.

Each episode runs on the in-process lockstep rig
(`ground_station.rigs.lockstep.run_episode`): the pymunk plant and the
robot's `RobotNode` + `Controller` on a python-can `virtual` bus.

The benchmark runs the acceptance sets on `paper10`: the sector policy on
seeded random (start, goal) pairs (driving the ground station's planned
waypoints as a mission, `--guidance path`, the default) and the cell policy on targets A-D from
seeded random starts, and reports success (goal reached with no wall
contact), contacts, and sim time against wall time.
"""

from __future__ import annotations

import argparse
import math
import random
from pathlib import Path

from firmware_py import robot_spec
from firmware_py.encoders import SectorEncoder
from firmware_py.policy import Policy
from ground_station.rigs.lockstep import run_episode

ROOT = Path(__file__).resolve().parents[2]


# --- acceptance sets ----------------------------------------------------------------

def free_cells(occ) -> list[tuple[int, int]]:
    h, w = occ.shape
    return [(c, r) for r in range(h) for c in range(w) if not occ[r][c]]


def random_pairs(occ, n: int, seed: int) -> list[tuple[tuple[int, int], float, tuple[int, int]]]:
    """n seeded (start cell, start heading rad, goal cell) with start != goal."""
    rng = random.Random(seed)
    cells = free_cells(occ)
    out: list[tuple[tuple[int, int], float, tuple[int, int]]] = []
    while len(out) < n:
        s, g = rng.sample(cells, 2)
        out.append((s, rng.uniform(-math.pi, math.pi), g))
    return out


def _centre_m(col: int, row: int, height: int, cell_mm: int) -> tuple[float, float]:
    x, y = robot_spec.cell_center_mm(col, row, height, cell_mm)
    return x / 1000, y / 1000


def run_sector_set(gm, policy: Policy, pairs: int, seed: int, max_sim_s: float, progress=None,
                   guidance: str = "path") -> list[dict]:
    """guidance "path": the robot gets the ground station's planned waypoints
    (ground_station.maps.planner.plan_waypoints) as a mission, as the sector
    policy is trained and evaluated; "direct": the goal alone."""
    from ground_station.maps.planner import guidance_from_metadata, plan_waypoints

    plan_kw = guidance_from_metadata(policy.metadata)  # the planner settings the policy trained with
    cell_mm = round(gm.cell_size_m * 1000)
    rows = []
    for i, (s, heading, g) in enumerate(random_pairs(gm.occ, pairs, seed)):
        sx, sy = _centre_m(*s, gm.height, cell_mm)
        goal = robot_spec.cell_center_mm(*g, gm.height, cell_mm)
        goals = plan_waypoints(gm, s, g, **plan_kw) if guidance == "path" else [goal]
        ep = run_episode(gm.occ, policy, (sx, sy, heading), goals, max_sim_s=max_sim_s, seed=seed + i)
        rows.append({"start": list(s), "heading_rad": round(heading, 3), "goal": list(g), "waypoints": len(goals),
                     "result": ep.result, "contacts": ep.contacts, "success": ep.success,
                     "sim_s": ep.sim_s, "wall_s": ep.wall_s,
                     "final_error_mm": round(ep.final_error_mm, 1)})
        if progress is not None:
            progress.update(1)
    return rows


def run_cell_set(gm, policy: Policy, starts: int, seed: int, max_sim_s: float, progress=None) -> list[dict]:
    cell_mm = policy.cell_mm
    rng = random.Random(seed)
    goals: dict[str, tuple[int, int]] = {name: cell for name, cell in gm.targets.items() if cell in policy.goals}
    cells = [c for c in free_cells(gm.occ) if c not in goals.values()]
    rows = []
    for i in range(starts):
        s = rng.choice(cells)
        heading = rng.uniform(-math.pi, math.pi)
        sx, sy = _centre_m(*s, gm.height, cell_mm)
        for name, g in goals.items():
            goal = robot_spec.cell_center_mm(*g, gm.height, cell_mm)
            ep = run_episode(gm.occ, policy, (sx, sy, heading), [goal], max_sim_s=max_sim_s,
                             seed=seed + i)
            rows.append({"start": list(s), "heading_rad": round(heading, 3), "target": name,
                         "goal": list(g), "result": ep.result, "contacts": ep.contacts,
                         "success": ep.success, "sim_s": ep.sim_s, "wall_s": ep.wall_s,
                         "final_error_mm": round(ep.final_error_mm, 1)})
            if progress is not None:
                progress.update(1)
    return rows


def twin_outcomes(gm, policy: Policy, rows: list[dict], max_periods: int = 2400,
                  guidance: str = "path") -> list[str]:
    """The same (start, heading, goal) episodes greedily on the training twin
    (`SectorNavEnv`, with the same waypoint guidance): "reached", "collision"
    or "timeout" each."""
    from ground_station.learn.envs.sector_env import SectorNavEnv
    from ground_station.maps.planner import guidance_from_metadata

    assert isinstance(policy.encoder, SectorEncoder)  # only sector policies have a twin
    env = SectorNavEnv(gm, encoder=policy.encoder, guidance=guidance, **guidance_from_metadata(policy.metadata))
    out = []
    for r in rows:
        state, _ = env.reset(seed=0, options={"start": tuple(r["start"]), "goal": tuple(r["goal"]),
                                              "heading": r["heading_rad"]})
        result = "timeout"
        for _ in range(max_periods):
            state, _, terminated, _, info = env.step(policy.best_action(state))
            if terminated:
                result = "reached" if info["success"] else "collision"
                break
        out.append(result)
    return out


def twin_outcomes_memory(gm, policy: Policy, rows: list[dict], max_periods: int = 2400) -> list[str]:
    """`twin_outcomes` for a sector-memory policy: the same episodes greedily
    on the twin with the jitted Bug memory (`evaluate_memory`'s kernel), direct."""
    import numpy as np

    from firmware_py.encoders import MemorySectorEncoder
    from ground_station.learn.sector.kernels import COLLISION, SUCCESS
    from ground_station.learn.sector.memory import eval_memory_kernel
    from ground_station.learn.sector.memory_train import memory_params
    from ground_station.learn.sector.twin import encoder_arrays, grid_of
    from ground_station.maps import octile_distances

    enc = policy.encoder
    assert isinstance(enc, MemorySectorEncoder)
    q = np.array(policy.table.tolist(), dtype=np.float64).reshape(policy.n_states, policy.n_actions)
    occ, h, w, c = grid_of(gm)
    starts = np.array([r["start"] for r in rows], dtype=np.int64).reshape(-1, 2)
    goals = np.array([r["goal"] for r in rows], dtype=np.int64).reshape(-1, 2)
    dists = np.stack([octile_distances(gm.occ, int(g[0]), int(g[1])) for g in goals]) if len(rows) \
        else np.zeros((0, h, w))
    headings = np.array([r["heading_rad"] for r in rows], dtype=np.float64)
    sectors, sensors, edges, which = encoder_arrays(enc.base)
    n = len(rows)
    outcome = np.zeros(n, dtype=np.int64)
    eval_memory_kernel(q, occ, h, w, c, dists, starts, goals, np.arange(n, dtype=np.int64), headings,
                       sectors, sensors, edges, np.ones_like(which), memory_params(enc), enc.base.n_states,
                       max_periods, 0.0, 0.0, max_periods + 1, outcome, np.zeros(n), np.zeros(n, dtype=np.int64),
                       np.zeros(n, dtype=np.int64))
    return ["reached" if o == SUCCESS else "collision" if o == COLLISION else "timeout" for o in outcome]


def _summary(rows: list[dict]) -> dict:
    n = len(rows)
    sim = sum(r["sim_s"] for r in rows)
    wall = sum(r["wall_s"] for r in rows)
    return {"episodes": n, "success": sum(r["success"] for r in rows),
            "success_rate": sum(r["success"] for r in rows) / n if n else 0.0,
            "reached": sum(r["result"] == "reached" for r in rows),
            "with_contact": sum(r["contacts"] > 0 for r in rows),
            "sim_s": sim, "wall_s": wall, "sim_per_wall": sim / wall if wall else 0.0}


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("hil", help="lockstep HIL acceptance episodes on paper10 (sector pairs, cell targets)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--map", default="paper10")
    p.add_argument("--sector-policy", default="policies:sector", metavar="FILE",  # or a sector-memory file
                   help="a .qtab file or policies:NAME (default %(default)s, shipped)")
    p.add_argument("--cell-policy", default="policies:paper10_cell", metavar="FILE",
                   help="a .qtab file or policies:NAME (default %(default)s, shipped)")
    p.add_argument("--pairs", type=int, default=50, help="sector: seeded random (start, goal) pairs")
    p.add_argument("--starts", type=int, default=20, help="cell: seeded random starts, each to every target")
    p.add_argument("--only", choices=("sector", "cell"), help="run one set only")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--guidance", choices=("path", "direct"), default="path",
                   help="sector: drive the planned waypoints as a mission (path) or the goal alone (direct)")
    p.add_argument("--compare-twin", action="store_true",
                   help="sector: also roll the same episodes out on the training twin and report agreement")
    p.add_argument("--max-sim-s", type=float, default=120.0, help="episode limit in sim seconds")
    p.add_argument("--json", metavar="FILE", help="write the result (with every episode) as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from firmware_py.policy import PolicyError, load_policy
    from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec
    from ground_station.bench.common import report
    from ground_station.errors import CliError
    from ground_station.maps import MapError, load_map

    try:
        gm = load_map(args.map)
    except MapError as exc:
        raise CliError(str(exc)) from None
    sets = [args.only] if args.only else ["sector", "cell"]
    result: dict = {"map": args.map, "seed": args.seed, "max_sim_s": args.max_sim_s, "guidance": args.guidance}
    rows_out: list[tuple[str, object]] = []
    for kind in sets:
        spec = args.sector_policy if kind == "sector" else args.cell_policy
        try:
            path = str(resolve_policy_spec(spec))
            pol = load_policy(path)
        except (PolicyError, ShippedPolicyError) as exc:
            raise CliError(f"{kind} policy {spec}: {exc}") from None
        if pol.kind != kind and not (kind == "sector" and pol.kind == "sector-memory"):
            raise CliError(f"{path} is a {pol.kind} policy, expected {kind}")
        if pol.kind == "sector-memory" and args.guidance != "direct":
            raise CliError(f"{path} is a sector-memory policy: it drives to the goal alone, use --guidance direct")
        if kind == "sector":
            total = args.pairs
            with tqdm(total=total, desc="sector pairs", unit="ep") as bar:
                rows = run_sector_set(gm, pol, args.pairs, args.seed, args.max_sim_s, bar, args.guidance)
        else:
            total = args.starts * sum(1 for c in gm.targets.values() if c in pol.goals)
            with tqdm(total=total, desc="cell targets", unit="ep") as bar:
                rows = run_cell_set(gm, pol, args.starts, args.seed, args.max_sim_s, bar)
        s = _summary(rows)
        if kind == "sector" and args.compare_twin:
            twin = twin_outcomes_memory(gm, pol, rows) if pol.kind == "sector-memory" else \
                twin_outcomes(gm, pol, rows, guidance=args.guidance)
            for r, t in zip(rows, twin, strict=True):
                r["twin"] = t
            s["twin_success"] = sum(t == "reached" for t in twin)
            s["twin_agreement"] = sum((t == "reached") == r["success"] for r, t in zip(rows, twin, strict=True))
        result[kind] = {"policy": path, "policy_id": f"0x{pol.policy_id:08x}", **s, "episodes_detail": rows}
        rows_out += [(f"{kind}: success (reached, no contact)", f"{s['success']}/{s['episodes']}"),
                     (f"{kind}: success_rate", s["success_rate"]),
                     (f"{kind}: reached", s["reached"]),
                     (f"{kind}: episodes with wall contact", s["with_contact"]),
                     (f"{kind}: sim_s total", s["sim_s"]),
                     (f"{kind}: wall_s total", s["wall_s"]),
                     (f"{kind}: sim/wall (x real time)", s["sim_per_wall"])]
        if "twin_success" in s:
            rows_out += [("sector: twin success (same episodes)", f"{s['twin_success']}/{len(rows)}"),
                         ("sector: HIL/twin success agreement", f"{s['twin_agreement']}/{len(rows)}")]
    report("hil", rows_out, result, args.json)
    return 0
