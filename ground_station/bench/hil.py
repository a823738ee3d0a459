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


def sector_episodes(gm, pairs: int, seed: int) -> list[dict]:
    """The seeded sector set: (start cell, heading, goal cell, episode seed) each."""
    return [{"start": list(s), "heading_rad": heading, "goal": list(g), "seed": seed + i}
            for i, (s, heading, g) in enumerate(random_pairs(gm.occ, pairs, seed))]


def cell_episodes(gm, policy: Policy, starts: int, seed: int) -> list[dict]:
    """The seeded cell set: every target from each of `starts` random starts."""
    rng = random.Random(seed)
    goals: dict[str, tuple[int, int]] = {name: cell for name, cell in gm.targets.items() if cell in policy.goals}
    cells = [c for c in free_cells(gm.occ) if c not in goals.values()]
    out = []
    for i in range(starts):
        s = rng.choice(cells)
        heading = rng.uniform(-math.pi, math.pi)
        out += [{"start": list(s), "heading_rad": heading, "target": name, "goal": list(g), "seed": seed + i}
                for name, g in goals.items()]
    return out


def run_batch(job: dict) -> list[dict]:
    """Run one batch of episodes (a campaign job: map, policy file, episode
    specs); each episode is seeded by its own spec, so a batch's rows do not
    depend on which worker runs it or what ran before."""
    from firmware_py.policy import load_policy
    from ground_station.maps import load_map
    from ground_station.maps.planner import guidance_from_metadata, plan_waypoints

    gm = load_map(job["map"])
    policy = load_policy(job["policy"])
    plan_kw = guidance_from_metadata(policy.metadata)  # the planner settings the policy trained with
    cell_mm = round(gm.cell_size_m * 1000) if job["kind"] == "sector" else policy.cell_mm
    rows = []
    for ep_spec in job["episodes"]:
        s = (int(ep_spec["start"][0]), int(ep_spec["start"][1]))
        g = (int(ep_spec["goal"][0]), int(ep_spec["goal"][1]))
        sx, sy = _centre_m(*s, gm.height, cell_mm)
        goal = robot_spec.cell_center_mm(*g, gm.height, cell_mm)
        if job["kind"] == "sector" and job["guidance"] == "path":
            goals = plan_waypoints(gm, s, g, **plan_kw)
        else:
            goals = [goal]
        ep = run_episode(gm.occ, policy, (sx, sy, ep_spec["heading_rad"]), goals, max_sim_s=job["max_sim_s"],
                         seed=ep_spec["seed"])
        row = {"start": list(s), "heading_rad": round(ep_spec["heading_rad"], 3)}
        row.update({"target": ep_spec["target"]} if "target" in ep_spec else {})
        row.update({"goal": list(g)})
        row.update({"waypoints": len(goals)} if job["kind"] == "sector" else {})
        row.update({"result": ep.result, "contacts": ep.contacts, "success": ep.success,
                    "sim_s": ep.sim_s, "wall_s": ep.wall_s, "final_error_mm": round(ep.final_error_mm, 1)})
        rows.append(row)
    return rows


def run_set(kind: str, map_name: str, policy_path: str, episodes: list[dict], max_sim_s: float,
            guidance: str = "path", engine=None, batch: int = 5, progress: bool = True) -> tuple[list[dict], dict]:
    """All episodes of one set, in batches of `batch` on `engine` (default: in
    this process). Returns the rows in episode order and the campaign stats."""
    from ground_station.campaign.engines import LocalEngine

    engine = engine or LocalEngine(1)
    jobs = [{"kind": kind, "map": map_name, "policy": policy_path, "guidance": guidance, "max_sim_s": max_sim_s,
             "episodes": episodes[i:i + batch]} for i in range(0, len(episodes), batch)]
    batches, stats = engine.map(run_batch, jobs, desc=f"{kind} episodes (batches of {batch})",
                                progress=progress, unit="batch")
    return [r for rows in batches for r in rows], stats.as_dict()


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


def _summary(rows: list[dict]) -> dict:
    n = len(rows)
    sim = sum(r["sim_s"] for r in rows)
    return {"episodes": n, "success": sum(r["success"] for r in rows),
            "success_rate": sum(r["success"] for r in rows) / n if n else 0.0,
            "reached": sum(r["result"] == "reached" for r in rows),
            "with_contact": sum(r["contacts"] > 0 for r in rows), "sim_s": sim}


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.campaign.engines import add_engine_arguments

    p = sub.add_parser("hil", help="lockstep HIL acceptance episodes on paper10 (sector pairs, cell targets)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--map", default="paper10")
    p.add_argument("--sector-policy", default="policies:sector", metavar="FILE",
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
    p.add_argument("--json", metavar="FILE",
                   help="write the result (with every episode) as JSON; where and how long it ran goes to "
                        "FILE's sibling *.campaign.json, so FILE is the same on every engine")
    p.add_argument("--batch", type=int, default=5, metavar="N", help="episodes per campaign job (default: 5)")
    add_engine_arguments(p, "episode batches")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:

    from ground_station.bench.common import report
    from ground_station.errors import CliError
    from ground_station.maps import MapError, load_map

    try:
        gm = load_map(args.map)
    except MapError as exc:
        raise CliError(str(exc)) from None
    from ground_station.campaign.engines import engine_from_args, write_campaign

    if args.batch < 1:
        raise CliError(f"--batch must be >= 1, got {args.batch}")
    sets = [args.only] if args.only else ["sector", "cell"]
    campaign: dict = {}
    result: dict = {"map": args.map, "seed": args.seed, "max_sim_s": args.max_sim_s, "guidance": args.guidance}
    engine = engine_from_args(args)
    try:
        rows_out = _run_sets(args, gm, sets, engine, result, campaign)
    finally:
        engine.close()
    report("hil", rows_out, result, args.json)
    write_campaign(args.json, campaign)
    return 0


def _run_sets(args: argparse.Namespace, gm, sets: list[str], engine, result: dict, campaign: dict) -> list:
    from firmware_py.policy import PolicyError, load_policy
    from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec
    from ground_station.errors import CliError

    rows_out: list[tuple[str, object]] = []
    for kind in sets:
        spec = args.sector_policy if kind == "sector" else args.cell_policy
        try:
            path = str(resolve_policy_spec(spec))
            pol = load_policy(path)
        except (PolicyError, ShippedPolicyError) as exc:
            raise CliError(f"{kind} policy {spec}: {exc}") from None
        if pol.kind != kind:
            raise CliError(f"{path} is a {pol.kind} policy, expected {kind}")
        episodes = (sector_episodes(gm, args.pairs, args.seed) if kind == "sector"
                    else cell_episodes(gm, pol, args.starts, args.seed))
        rows, stats = run_set(kind, args.map, path, episodes, args.max_sim_s, args.guidance, engine, args.batch)
        campaign[kind] = {**stats, "episode_wall_s": [r.pop("wall_s") for r in rows]}
        s = _summary(rows)
        if kind == "sector" and args.compare_twin:
            twin = twin_outcomes(gm, pol, rows, guidance=args.guidance)
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
                     (f"{kind}: episode wall_s total", sum(campaign[kind]["episode_wall_s"])),
                     (f"{kind}: sim/wall per episode (x real time)",
                      s["sim_s"] / max(1e-9, sum(campaign[kind]["episode_wall_s"]))),
                     (f"{kind}: campaign wall_s ({stats['engine']}, {stats['workers']} workers)", stats["wall_s"]),
                     (f"{kind}: campaign speedup over one core (job time / wall)", stats["speedup_over_one_core"])]
        if "twin_success" in s:
            rows_out += [("sector: twin success (same episodes)", f"{s['twin_success']}/{len(rows)}"),
                         ("sector: HIL/twin success agreement", f"{s['twin_agreement']}/{len(rows)}")]
    return rows_out
