"""`qnav bench hil`: lockstep hardware-in-the-loop episodes, in one process.

Each episode runs on the in-process lockstep rig
(`ground_station.lab.rigs.lockstep.run_episode`): the pymunk plant and the
robot's `RobotNode` + `Controller` on a python-can `virtual` bus.

The benchmark runs the acceptance sets on `paper10`: the sector policy on
seeded random (start, goal) pairs (driving the ground station's planned
waypoints as a mission, `--guidance path`, the default) and the cell policy
on targets A-D from seeded random starts, and reports success (goal reached
with no wall contact), contacts, and sim time against wall time.

`--profile ideal|realistic` names the plant's wheel and sensor error
(`sim_bridge/profiles.py`; realistic: one encoder 3 % long, 10 % slip, 10 mm
range noise, 2 % dropout); `--profile FILE.toml` (repeatable with one of
those) a robot profile (docs/robot-profile.md): the sim and the robot play
that robot (body, wheels, sensors, boards), the planned waypoints keep its
body clear, and the policies must be ones it runs (`firmware_py.needs`; one
line, exit 2, otherwise). The episodes are the same seeded ones whatever the
robot. `--baselines seek,vfh,direct` runs the bench nav controllers
(`ground_station.lab.nav.controllers`: hand-written tables on the sector
policy's encoder, and the policy on the goal bearing) on the same sector
episodes, each a row group of its own. The robot localises on the map its
policy carries (`firmware_py/control/localiser.py`); `--compare-odometry`
runs the same episodes again with the localiser off (dead reckoning only, as
before) as the baseline. Ground truth against belief: the distance from the
true position to the goal at the end (`final_error_mm`, bounded below by the
goal tolerance), the localisation error |true - believed| at the end and its
maximum while driving, and the dead-reckoning error. `step_cpu_us` is the
thread CPU time of `Controller.step` per tick (localiser included).
"""

from __future__ import annotations

import argparse
import math
import random
import time
from collections.abc import Sequence
from pathlib import Path
from typing import cast

from firmware_py import robot_spec
from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.policy import Policy
from firmware_py.vehicle import VehicleConfig
from ground_station.lab.rigs.lockstep import run_episode
from sim_bridge.profiles import PlantProfile

ROOT = Path(__file__).resolve().parents[3]


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


def _row(ep) -> dict:
    """The figures every episode row carries (ground truth vs belief, tick CPU)."""
    cpu = sorted(ep.step_cpu_us)
    return {"result": ep.result, "contacts": ep.contacts, "success": ep.success,
            "sim_s": ep.sim_s, "wall_s": ep.wall_s,
            "final_error_mm": round(ep.final_error_mm, 1),
            "belief_error_mm": round(ep.belief_error_mm, 1),
            "belief_error_max_mm": round(ep.belief_error_max_mm, 1),
            "odom_error_mm": round(ep.odom_error_mm, 1),
            "step_cpu_p50_us": round(cpu[len(cpu) // 2], 1) if cpu else 0.0,
            "step_cpu_p99_us": round(_pct(cpu, 0.99), 1) if cpu else 0.0,
            "step_cpu_max_us": round(cpu[-1], 1) if cpu else 0.0,
            "_cpu": ep.step_cpu_us}


def clearance_mm(gm, poses: Sequence[tuple], radius_mm: float = robot_spec.ROBOT_RADIUS_MM) -> float:
    """Smallest distance (mm) between the robot's true outline (a disc of
    `radius_mm`) and a wall over an episode (`Episode.poses`; negative:
    overlap, i.e. contact)."""
    from firmware_py.control.localiser import LikelihoodField
    from firmware_py.mapdata import grid_from_rows

    cell_mm = round(gm.cell_size_m * 1000)
    rows = ["".join("@" if v else "." for v in row) for row in gm.occ.tolist()]
    field = LikelihoodField(grid_from_rows(rows, cell_mm), cell_mm, 1.0, 1.0, 1.0, 1.0)  # distances only
    step = max(1, len(poses) // 2000)
    d = min((field.distance_mm(p[1], p[2], 2) for p in poses[::step]), default=math.inf)
    return d - radius_mm


def write_belief_png(gm, ep, goals_mm: list[tuple[int, int]], path: str, title: str = "") -> None:
    """The map with the true path (sim), the believed path (localiser) and the
    dead-reckoning path of one episode, and the localisation error over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = ep.poses
    t = [r[0] / 1e6 for r in p]
    w_m, h_m = gm.width * gm.cell_size_m, gm.height * gm.cell_size_m
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 6), dpi=100, gridspec_kw={"width_ratios": [1, 1]})
    ax.imshow(gm.occ, cmap="Greys", vmin=0, vmax=1.4, extent=(0, w_m, 0, h_m), origin="upper",
              interpolation="nearest")
    ax.plot([r[1] / 1000 for r in p], [r[2] / 1000 for r in p], "-", color="tab:blue", lw=1.8, label="true (sim)")
    ax.plot([r[3] / 1000 for r in p], [r[4] / 1000 for r in p], "--", color="tab:orange", lw=1.2,
            label="believed (localiser)")
    ax.plot([r[5] / 1000 for r in p], [r[6] / 1000 for r in p], ":", color="tab:red", lw=1.2,
            label="dead reckoning")
    for gx, gy in goals_mm:
        ax.plot(gx / 1000, gy / 1000, "*", color="tab:green", ms=10)
    ax.set_xlim(0, w_m)
    ax.set_ylim(0, h_m)
    ax.set_aspect("equal")
    ax.set_xlabel("x east (m)")
    ax.set_ylabel("y north (m)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title, fontsize=9)
    ax2.plot(t, [math.hypot(r[1] - r[3], r[2] - r[4]) for r in p], color="tab:orange", label="|true - believed|")
    ax2.plot(t, [math.hypot(r[1] - r[5], r[2] - r[6]) for r in p], color="tab:red", label="|true - dead reckoning|")
    ax2.set_xlabel("sim time (s)")
    ax2.set_ylabel("position error (mm)")
    ax2.legend(fontsize=8)
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _pct(sorted_vals: Sequence[float], q: float) -> float:
    return sorted_vals[min(len(sorted_vals) - 1, int(q * len(sorted_vals)))]


def sector_episodes(gm, pairs: int, seed: int) -> list[dict]:
    """The seeded sector set: (start cell, heading, goal cell, episode seed) each."""
    return [{"index": i, "start": list(s), "heading_rad": heading, "goal": list(g), "seed": seed + i}
            for i, (s, heading, g) in enumerate(random_pairs(gm.occ, pairs, seed))]


def cell_episodes(gm, policy: Policy, starts: int, seed: int) -> list[dict]:
    """The seeded cell set: every target from each of `starts` random starts."""
    rng = random.Random(seed)
    goals: dict[str, tuple[int, int]] = {name: cell for name, cell in gm.targets.items() if cell in policy.goals}
    cells = [c for c in free_cells(gm.occ) if c not in goals.values()]
    out: list[dict] = []
    for i in range(starts):
        s = rng.choice(cells)
        heading = rng.uniform(-math.pi, math.pi)
        out += [{"index": i, "start": list(s), "heading_rad": heading, "target": name, "goal": list(g),
                 "seed": seed + i} for name, g in goals.items()]
    return out


def run_episodes(gm, policy: Policy, kind: str, specs: list[dict], max_sim_s: float, guidance: str = "path",
                 profile: PlantProfile | None = None, localise: bool = True, png_dir: str | None = None,
                 vehicle: VehicleConfig | None = None, progress=None, robot=None,
                 plan_meta: dict | None = None) -> list[dict]:
    """Run the episodes `specs` (from `sector_episodes`/`cell_episodes`); one
    row each. Every episode is seeded by its own spec, so a row does not
    depend on what ran before it or where. `robot`: the robot profile
    (firmware_py.profile.RobotProfile) the sim and the robot play (None: the
    built-in robot); `plan_meta`: the metadata whose planner settings the
    waypoints use (default the policy's)."""
    from ground_station.maps.planner import guidance_from_metadata, plan_waypoints

    # the planner settings the policy trained with, around the robot's own body
    plan_kw = guidance_from_metadata(policy.metadata if plan_meta is None else plan_meta)
    radius = robot.geometry.robot_radius_mm if robot is not None else robot_spec.ROBOT_RADIUS_MM
    plan_kw["radius_mm"] = radius
    cell_mm = round(gm.cell_size_m * 1000) if kind == "sector" else policy.cell_mm
    rows = []
    for spec in specs:
        s = (int(spec["start"][0]), int(spec["start"][1]))
        g = (int(spec["goal"][0]), int(spec["goal"][1]))
        sx, sy = _centre_m(*s, gm.height, cell_mm)
        goal = robot_spec.cell_center_mm(*g, gm.height, cell_mm)
        goals = plan_waypoints(gm, s, g, **plan_kw) if kind == "sector" and guidance == "path" else [goal]
        ep = run_episode(gm.occ, policy, (sx, sy, spec["heading_rad"]), goals, max_sim_s=max_sim_s,
                         seed=spec["seed"], profile=profile, localise=localise, vehicle=vehicle, robot=robot)
        row: dict = {"start": list(s), "heading_rad": round(spec["heading_rad"], 3)}
        if kind == "sector":
            row.update(goal=list(g), waypoints=len(goals))
        else:
            row.update(target=spec["target"], goal=list(g))
        row.update(**_row(ep), clearance_mm=round(clearance_mm(gm, ep.poses, radius), 1))
        rows.append(row)
        if png_dir:
            name = (f"sector_{spec['index']:03d}.png" if kind == "sector"
                    else f"cell_{spec['index']:03d}_{spec['target']}.png")
            write_belief_png(gm, ep, goals if kind == "sector" else [goal], str(Path(png_dir) / name),
                             f"{kind} {spec['index']}: {s} -> {g}, {ep.result}, seed {spec['seed']}")
        if progress is not None:
            progress.update(1)
    return rows


def run_batch(job: dict) -> list[dict]:
    """One campaign job: a batch of episode specs with everything needed to
    run them in a fresh worker (map, policy file, profile name, settings)."""
    from firmware_py.policy import load_policy
    from firmware_py.profile import load_profile
    from ground_station.maps import load_map
    from sim_bridge.profiles import profile

    vehicle = VehicleConfig(goal_tolerance_mm=job["goal_tolerance_mm"]) if job["goal_tolerance_mm"] else None
    robot = load_profile(job["robot"]) if job.get("robot") else None
    pol = load_policy(job["policy"])
    plan_meta = None
    guidance = job["guidance"]
    if job.get("controller"):  # a baseline on the policy's encoder, waypoints planned as for the policy
        from ground_station.lab.nav.controllers import standard_controllers

        ctrl = standard_controllers(pol, (job["controller"],))[0]
        plan_meta, guidance = pol.metadata, ctrl.guidance
        pol = ctrl.policy(job["map"])
    return run_episodes(load_map(job["map"]), pol, job["kind"], job["episodes"],
                        job["max_sim_s"], guidance, profile(job["profile"]), job["localise"],
                        job["png_dir"], vehicle, robot=robot, plan_meta=plan_meta)


# Per-episode and summary figures that are measurements of this machine (CPU,
# wall time): kept out of the result file, which depends only on the seeded
# episodes, and written to FILE.campaign.json.
TIMING_KEYS = ("wall_s", "sim_per_wall", "step_cpu_p50_us", "step_cpu_p99_us", "step_cpu_max_us", "_cpu")


def split_timing(d: dict) -> dict:
    """Remove the timing keys from `d` and return them."""
    return {k: d.pop(k) for k in TIMING_KEYS if k in d}


def run_set(kind: str, job: dict, episodes: list[dict], engine, batch: int, tag: str = "") -> tuple[list[dict], dict]:
    """All episodes of one set on `engine`, `batch` per job; rows in episode order."""
    jobs = [{**job, "kind": kind, "episodes": episodes[i:i + batch]} for i in range(0, len(episodes), batch)]
    batches, stats = engine.map(run_batch, jobs, desc=f"{kind} episodes{tag} (batches of {batch})", unit="batch")
    return [r for rows in batches for r in rows], stats.as_dict()


def run_global_set(gm, policy: Policy, n: int, seed: int, limit_s: float = 10.0, progress=None,
                   profile: PlantProfile | None = None, converged_mm: float = 150.0, robot=None) -> list[dict]:
    """Global localisation from unknown seeded starts: the robot is armed,
    told its pose is unknown (`Controller.localise_global`, exploring), and
    the episode runs `limit_s` sim seconds. Converged: the localiser reports
    localised by then with |true - believed| <= `converged_mm`, and no
    wall contact."""
    from ground_station.lab.rigs.lockstep import LockstepRig

    rows = []
    for i, (s, heading, _) in enumerate(random_pairs(gm.occ, n, seed)):
        sx, sy = _centre_m(*s, gm.height, round(gm.cell_size_m * 1000))
        t_wall = time.perf_counter()
        with LockstepRig(gm.occ, policy, (sx, sy, heading), [], seed=seed + i, profile=profile,
                         robot=robot) as rig:
            for _ in range(3):  # every input fresh before arming
                rig.tick()
            ok, why = rig.ctrl.arm()
            ok2, why2 = rig.ctrl.localise_global()
            t0 = rig.time_us
            loc = rig.ctrl.loc
            t_loc: float | None = None
            err_loc = math.nan
            while rig.time_us - t0 < limit_s * 1e6:
                rig.tick()
                if loc is not None and loc.localised and t_loc is None:
                    p = rig.poses[-1]
                    t_loc = (rig.time_us - t0) / 1e6
                    err_loc = math.hypot(p[1] - p[3], p[2] - p[4])
            p = rig.poses[-1]
            err_end = math.hypot(p[1] - p[3], p[2] - p[4])
            contacts = rig.plant.world.contact_events
            cpu = sorted(rig.ctrl.step_cpu_ns)
        rows.append({"start": list(s), "heading_rad": round(heading, 3), "armed": ok or why,
                     "global": ok2 or why2, "localised_after_s": t_loc,
                     "error_at_localised_mm": round(err_loc, 1), "error_at_end_mm": round(err_end, 1),
                     "contacts": contacts,
                     "success": t_loc is not None and err_loc <= converged_mm and contacts == 0,
                     "step_cpu_p99_us": round(_pct(cpu, 0.99) / 1000, 1) if cpu else 0.0,
                     "wall_s": time.perf_counter() - t_wall})
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

    assert policy.kind == "sector"  # only sector policies have this twin
    env = SectorNavEnv(gm, encoder=cast(SectorEncoder, policy.encoder), guidance=guidance,
                       **guidance_from_metadata(policy.metadata))
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


def twin_outcomes_gridbug(gm, policy: Policy, rows: list[dict]) -> list[str]:
    """`twin_outcomes` for a sector-memory policy: the same episodes
    greedily on the grid twin (`evaluate_gridbug`'s kernel; the initial
    heading turned to the nearest grid direction, as the robot does)."""
    import numpy as np

    from firmware_py.kinds.sector_memory.gridbug import GridBugEncoder, grid_dir_of
    from ground_station.learn.sector_memory.kernels import COLLISION, SUCCESS, eval_kernel
    from ground_station.learn.sector_memory.trainer import encoder_params

    assert policy.kind == "sector-memory"
    enc = cast(GridBugEncoder, policy.encoder)
    q = np.array(policy.table.tolist(), dtype=np.float64).reshape(policy.n_states, policy.n_actions)
    n = len(rows)
    starts = np.array([r["start"] for r in rows], dtype=np.int64).reshape(-1, 2)
    goals = np.array([r["goal"] for r in rows], dtype=np.int64).reshape(-1, 2)
    dirs = np.array([grid_dir_of(round(r["heading_rad"] * 1000)) for r in rows], dtype=np.int64)
    outcome = np.zeros(n, dtype=np.int64)
    eval_kernel(q, np.ascontiguousarray(gm.occ, dtype=np.uint8), gm.height, gm.width, encoder_params(enc),
                starts, goals, dirs, 10 * len(gm.free_cells()), outcome, np.zeros(n, dtype=np.int64),
                np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64))
    return ["reached" if o == SUCCESS else "collision" if o == COLLISION else "timeout" for o in outcome]


def _summary(rows: list[dict]) -> dict:
    n = len(rows)
    sim = sum(r["sim_s"] for r in rows)
    wall = sum(r["wall_s"] for r in rows)
    cpu = sorted(v for r in rows for v in r.pop("_cpu", []))
    reached = [r for r in rows if r["result"] == "reached"]

    def med_max(key: str) -> tuple[float, float]:
        vals = sorted(r[key] for r in reached)
        return (vals[len(vals) // 2], vals[-1]) if vals else (math.nan, math.nan)

    fin, bel, odo = med_max("final_error_mm"), med_max("belief_error_mm"), med_max("odom_error_mm")
    clear = min((r["clearance_mm"] for r in rows if "clearance_mm" in r), default=math.nan)
    return {"episodes": n, "success": sum(r["success"] for r in rows),
            "success_rate": sum(r["success"] for r in rows) / n if n else 0.0,
            "reached": len(reached),
            "with_contact": sum(r["contacts"] > 0 for r in rows),
            "contacts": sum(r["contacts"] for r in rows),
            "goal_error_median_mm": fin[0], "goal_error_max_mm": fin[1],
            "belief_error_median_mm": bel[0], "belief_error_max_mm": bel[1],
            "odom_error_median_mm": odo[0], "odom_error_max_mm": odo[1], "clearance_min_mm": clear,
            "step_cpu_p50_us": _pct(cpu, 0.5) if cpu else 0.0, "step_cpu_p99_us": _pct(cpu, 0.99) if cpu else 0.0,
            "step_cpu_max_us": cpu[-1] if cpu else 0.0,
            "sim_s": sim, "wall_s": wall, "sim_per_wall": sim / wall if wall else 0.0}


def _summary_rows(label: str, s: dict, stats: dict | None = None) -> list[tuple[str, object]]:
    return [(f"{label}: success (reached, no contact)", f"{s['success']}/{s['episodes']}"),
            (f"{label}: success_rate", s["success_rate"]),
            (f"{label}: reached", s["reached"]),
            (f"{label}: episodes with wall contact", s["with_contact"]),
            (f"{label}: goal error at the end, median / max (mm, true)",
             f"{s['goal_error_median_mm']:.0f} / {s['goal_error_max_mm']:.0f}"),
            (f"{label}: localisation error |true-believed| at the end, median / max (mm)",
             f"{s['belief_error_median_mm']:.0f} / {s['belief_error_max_mm']:.0f}"),
            (f"{label}: dead-reckoning error at the end, median / max (mm)",
             f"{s['odom_error_median_mm']:.0f} / {s['odom_error_max_mm']:.0f}"),
            (f"{label}: smallest true clearance to a wall (mm)", f"{s['clearance_min_mm']:.0f}"),
            (f"{label}: Controller.step CPU p50 / p99 / max (us)",
             f"{s['step_cpu_p50_us']:.0f} / {s['step_cpu_p99_us']:.0f} / {s['step_cpu_max_us']:.0f}"),
            (f"{label}: sim_s total", s["sim_s"]),
            (f"{label}: wall_s total", s["wall_s"]),
            (f"{label}: sim/wall (x real time)", s["sim_per_wall"])] + ([
            (f"{label}: campaign wall_s ({stats['engine']}, {stats['workers']} workers)", stats["wall_s"]),
            (f"{label}: campaign speedup over one core (job time / wall)", stats["speedup_over_one_core"])]
            if stats else [])


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.lab.campaign.engines import add_engine_arguments

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
    p.add_argument("--profile", action="append", default=None, metavar="ideal|realistic|FILE.toml",
                   help="plant wheel/sensor error: ideal or realistic (sim_bridge/profiles.py; default ideal); "
                        "or a robot profile FILE.toml the sim and the robot play (docs/robot-profile.md; the "
                        "policies must be ones it runs). Repeatable: one of each")
    p.add_argument("--baselines", metavar="NAMES", default="",
                   help="sector: also run these bench nav controllers on the same episodes (comma-separated: "
                        "seek, vfh, direct, seek_local, vfh_local)")
    p.add_argument("--no-localiser", action="store_true",
                   help="drive on dead reckoning only (the localiser off, as before the map travelled)")
    p.add_argument("--goal-tolerance-mm", type=int, metavar="MM",
                   help="the robot's GOAL_TOL_MM for these episodes (default: the robot's, "
                        f"{robot_spec.GOAL_TOLERANCE_MM}); the true end error cannot be below it by much")
    p.add_argument("--png-dir", metavar="DIR",
                   help="write one PNG per episode: true, believed and dead-reckoning paths, error over time")
    p.add_argument("--global-starts", type=int, default=0, metavar="N",
                   help="also N seeded global-localisation episodes (unknown start, exploring; the sector "
                        "policy's map): converged within --global-limit-s with |true - believed| <= 150 mm")
    p.add_argument("--global-limit-s", type=float, default=10.0, help="sim seconds a global episode may take")
    p.add_argument("--compare-odometry", action="store_true",
                   help="also run the same episodes with the localiser off and report both")
    p.add_argument("--json", metavar="FILE",
                   help="write the result (with every episode) as JSON; timings and where the jobs ran go to "
                        "FILE's sibling *.campaign.json, so FILE is the same on every engine")
    p.add_argument("--batch", type=int, default=5, metavar="N", help="episodes per campaign job (default: 5)")
    add_engine_arguments(p, "episode batches")
    p.set_defaults(func=run)


def _run_sets(args: argparse.Namespace, gm, pol_sets: list[str], job: dict, engine, result: dict,
              campaign: dict) -> list[tuple[str, object]]:
    """The sector and/or cell sets on `engine`: fills `result` (deterministic)
    and `campaign` (timing, where jobs ran); returns the table rows."""
    from firmware_py.policy import PolicyError, load_policy
    from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec
    from ground_station.errors import CliError

    rows_out: list[tuple[str, object]] = []
    for kind in pol_sets:
        spec = args.sector_policy if kind == "sector" else args.cell_policy
        try:
            path = str(resolve_policy_spec(spec))
            pol = load_policy(path)
        except (PolicyError, ShippedPolicyError) as exc:
            raise CliError(f"{kind} policy {spec}: {exc}") from None
        if pol.kind != kind and not (kind == "sector" and pol.kind == "sector-memory"):
            raise CliError(f"{path} is a {pol.kind} policy, expected {kind}")
        if pol.kind == "sector-memory" and args.guidance != "direct":
            raise CliError(f"{path} is a {pol.kind} policy: it drives to the goal alone, use --guidance direct")
        if args.robot is not None:  # the robot's own check: a policy it would refuse is not benched on it
            from firmware_py.needs import needs_mismatch, needs_of

            why = needs_mismatch(needs_of(pol), args.robot)
            if why:
                raise CliError(f"{kind} policy {spec} on --profile {args.robot.source}: {why}")
        if kind == "cell" and not args.no_localiser and pol.map_grid is None:
            print(f"note: {path} carries no map (qnav policy attach-map): the cell set runs on dead reckoning")
        main_rows: list[dict] = []
        s: dict = {}
        runs = [not args.no_localiser] + ([False] if args.compare_odometry and not args.no_localiser else [])
        episodes = (sector_episodes(gm, args.pairs, args.seed) if kind == "sector"
                    else cell_episodes(gm, pol, args.starts, args.seed))
        for localise in runs:
            tag = "" if localise == runs[0] else " (odometry only)"
            rows, stats = run_set(kind, {**job, "policy": path, "localise": localise,
                                         "png_dir": None if tag else args.png_dir}, episodes, engine, args.batch, tag)
            summary = _summary(rows)
            timing = split_timing(summary)
            campaign[kind + ("_odometry_only" if tag else "")] = {
                **stats, "summary": timing, "episodes": [split_timing(r) for r in rows]}
            if tag:
                result[kind]["odometry_only"] = {**summary, "episodes_detail": rows}
                rows_out += _summary_rows(f"{kind} odometry only", {**summary, **timing}, stats)
                continue
            s = summary
            main_rows = rows
            result[kind] = {"policy": path, "policy_id": f"0x{pol.policy_id:08x}",
                            "localiser": localise and pol.map_grid is not None, **s}
            rows_out += _summary_rows(kind, {**s, **timing}, stats)
        rows = main_rows
        if kind == "sector" and args.compare_twin:
            if pol.kind == "sector-memory":
                twin = twin_outcomes_gridbug(gm, pol, rows)
            else:
                twin = twin_outcomes(gm, pol, rows, guidance=args.guidance)
            for r, t in zip(rows, twin, strict=True):
                r["twin"] = t
            s["twin_success"] = sum(t == "reached" for t in twin)
            s["twin_agreement"] = sum((t == "reached") == r["success"] for r, t in zip(rows, twin, strict=True))
        result[kind].update({k: s[k] for k in ("twin_success", "twin_agreement") if k in s}, episodes_detail=rows)
        if "twin_success" in s:
            rows_out += [("sector: twin success (same episodes)", f"{s['twin_success']}/{len(rows)}"),
                         ("sector: HIL/twin success agreement", f"{s['twin_agreement']}/{len(rows)}")]
        for name in args.baseline_names if kind == "sector" else ():
            brows, stats = run_set(kind, {**job, "policy": path, "localise": not args.no_localiser,
                                          "png_dir": None, "controller": name},
                                   episodes, engine, args.batch, f" ({name})")
            bs = _summary(brows)
            timing = split_timing(bs)
            campaign[f"{kind}_{name}"] = {**stats, "summary": timing, "episodes": [split_timing(r) for r in brows]}
            result.setdefault("baselines", {})[name] = {**bs, "episodes_detail": brows}
            rows_out += _baseline_rows(name, bs)
    return rows_out


def _baseline_rows(name: str, s: dict) -> list[tuple[str, object]]:
    return [(f"{name} (baseline): success (reached, no contact)", f"{s['success']}/{s['episodes']}"),
            (f"{name} (baseline): reached", s["reached"]),
            (f"{name} (baseline): episodes with wall contact", s["with_contact"]),
            (f"{name} (baseline): smallest true clearance to a wall (mm)", f"{s['clearance_min_mm']:.0f}")]


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from firmware_py.policy import PolicyError, load_policy
    from firmware_py.profile import load_profile
    from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec
    from ground_station.errors import CliError
    from ground_station.lab.bench.common import report
    from ground_station.lab.bench.nav import _profiles
    from ground_station.lab.campaign.engines import engine_from_args, write_campaign
    from ground_station.lab.nav.controllers import CONTROLLER_NAMES, EXTRA_CONTROLLERS
    from ground_station.maps import MapError, load_map
    from sim_bridge.profiles import profile

    plant, robot_file = _profiles(args.profile)
    args.profile = plant or "ideal"
    args.baseline_names = [n.strip() for n in args.baselines.split(",") if n.strip()]
    bad = [n for n in args.baseline_names if n not in CONTROLLER_NAMES + EXTRA_CONTROLLERS or n == "learnt"]
    if bad:
        raise CliError(f"--baselines {','.join(bad)}: expected some of "
                       f"{', '.join(n for n in CONTROLLER_NAMES + EXTRA_CONTROLLERS if n != 'learnt')}")
    try:
        gm = load_map(args.map)
        prof = profile(args.profile)
        args.robot = load_profile(robot_file) if robot_file is not None else None
    except (MapError, ValueError) as exc:
        raise CliError(str(exc)) from None
    sets = [args.only] if args.only else ["sector", "cell"]
    result: dict = {"map": args.map, "seed": args.seed, "max_sim_s": args.max_sim_s, "guidance": args.guidance,
                    "profile": prof.to_dict(), "localiser": not args.no_localiser}
    if robot_file is not None:
        result["robot"] = robot_file
    if args.png_dir:
        Path(args.png_dir).mkdir(parents=True, exist_ok=True)
    if args.goal_tolerance_mm is not None and not 1 <= args.goal_tolerance_mm <= 10_000:
        raise CliError(f"--goal-tolerance-mm {args.goal_tolerance_mm}: expected 1..10000")
    result["goal_tolerance_mm"] = args.goal_tolerance_mm or robot_spec.GOAL_TOLERANCE_MM
    if args.batch < 1:
        raise CliError(f"--batch must be >= 1, got {args.batch}")
    rows_out: list[tuple[str, object]] = []
    job = {"map": args.map, "guidance": args.guidance, "max_sim_s": args.max_sim_s, "profile": args.profile,
           "goal_tolerance_mm": args.goal_tolerance_mm, "robot": robot_file}
    campaign: dict = {}
    with engine_from_args(args) as engine:
        rows_out += _run_sets(args, gm, pol_sets=sets, job=job, engine=engine, result=result, campaign=campaign)
    if args.global_starts > 0:
        try:
            pol = load_policy(str(resolve_policy_spec(args.sector_policy)))
        except (PolicyError, ShippedPolicyError) as exc:
            raise CliError(f"sector policy {args.sector_policy}: {exc}") from None
        if pol.map_grid is None:
            raise CliError(f"{args.sector_policy} carries no map: global localisation needs one (qnav policy attach-map)")
        with tqdm(total=args.global_starts, desc="global localisation", unit="ep") as bar:
            grows = run_global_set(gm, pol, args.global_starts, args.seed, args.global_limit_s, bar, prof,
                                   robot=args.robot)
        conv = sum(r["success"] for r in grows)
        times = sorted(r["localised_after_s"] for r in grows if r["localised_after_s"] is not None)
        cpu = sorted(r["step_cpu_p99_us"] for r in grows)
        campaign["global"] = {"episodes": [split_timing(r) for r in grows]}
        result["global"] = {"episodes": len(grows), "converged": conv, "converged_rate": conv / len(grows),
                            "limit_s": args.global_limit_s, "localised": len(times),
                            "localised_after_s_median": times[len(times) // 2] if times else None,
                            "episodes_detail": grows}
        rows_out += [(f"global: converged within {args.global_limit_s:g} s (<= 150 mm)", f"{conv}/{len(grows)}"),
                     ("global: reported localised (any error)", f"{len(times)}/{len(grows)}"),
                     ("global: time to localised, median (sim s)",
                      f"{times[len(times) // 2]:.1f}" if times else "-"),
                     ("global: Controller.step CPU p99 per episode, median (us)", f"{cpu[len(cpu) // 2]:.0f}")]
    report("hil", rows_out, result, args.json)
    write_campaign(args.json, campaign)
    return 0
