"""`qnav bench nav`: controllers against unmapped static and moving obstacles.

Every controller (`learnt` sector policy, `seek` table, `vfh` reactive
baseline, `direct` = the learnt table without waypoints; see
`ground_station.lab.nav.controllers`) drives the same seeded scenario episodes
(`ground_station.lab.nav.scenario`: start, goal, the planner's waypoints on the
known map, up to K detourable static discs, M movers) on each map: on the
kinematic twin (`--episodes` per map) and, with `--hil`, on the lockstep
pymunk rig with the robot's own controller (`--hil-episodes` per
controller, spread over the maps). Prints a table, writes JSON (`--json`)
and a PNG comparing the controllers (`--png`, default: the JSON's name with
.png).

Every shipped navigation kind runs: a `sector` policy (`--policy
policies:sector`, the default) with the controllers above; a `sector-memory`
policy (`--policy policies:sector_memory`, the direct setting: the goal
alone, the robot on its own map) as `learnt` beside `rule`, the same mode
rules with hand-written moves, in HIL only (`--hil` required: its trainer's
twin is a grid world without the scenario's discs and movers).

`--blocked detour|none|both`: blocked-passage episodes instead
(`scenario.blocked_episodes`): one disc closes a door, corridor or aisle on
the planned route, and a route around it exists elsewhere (`detour`) or not
at all (`none`: the right answer is to report "no route"); `both` alternates
the two labels. `--obstacles` then defaults to 0 extra discs. A map without
such an episode is named on stderr and skipped.

JSON: `scenario` (maps, obstacles, movers, seed, episodes, blocked), per
controller (`learnt`, `seek`, `vfh`, `direct`) the twin figures over all
maps (`success_rate`, `collision_rate`, `path_ratio_mean`, `episodes`,
`time_to_goal_mean_s`, `near_miss_rate`, `no_route_rate`, `outcomes`, with
`--blocked` a `blocked` object per label), `per_map` the same per map,
`paired_vs_learnt` (exact McNemar on the same twin episodes) and
`paired_time_vs_learnt` (time to goal where both succeeded: who was sooner,
the median difference, a sign test), and with `--hil` a `hil` object with
the same per-controller keys, `per_map`, `paired_vs_learnt` (exact McNemar
on the same episodes) and `twin_same_episodes` (the twin on exactly the HIL
episodes).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ground_station.lab.nav.scenario import Episode, MoverStyle
    from ground_station.maps import GridMap

DEFAULT_MAPS = ("paper10", "rooms-16x16-s1", "trap-16x16-s1", "random-16x16-s1", "maze-16x16-s1")
KEYS = ("success_rate", "collision_rate", "path_ratio_mean", "time_to_goal_mean_s", "near_miss_rate")


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.lab.campaign.engines import add_engine_arguments

    p = sub.add_parser("nav", help="controllers vs unmapped static and moving obstacles (twin, --hil lockstep)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--map", action="append", metavar="NAME|PATH",
                   help=f"map (repeatable; built-in, generator spec or .map file); default {', '.join(DEFAULT_MAPS)}")
    p.add_argument("--obstacles", type=int, default=None, metavar="K",
                   help="static detourable discs per episode (default 3; 0 with --blocked)")
    p.add_argument("--blocked", choices=("detour", "none", "both"), default=None,
                   help="blocked-passage episodes: a disc closes a narrow passage on the route, with a route "
                        "elsewhere (detour), none at all (none) or half each (both); default: off")
    p.add_argument("--movers", type=int, default=2, metavar="M", help="moving discs per episode (default %(default)s)")
    p.add_argument("--mover-speed", default=None, metavar="LO,HI",
                   help="movers' speed range, mm/s (default 300,600: a pedestrian's pace)")
    p.add_argument("--no-yield", action="store_true",
                   help="movers walk their own line through the robot's path and stop only on contact, instead "
                        "of stepping aside (sim_bridge/obstacles.py)")
    p.add_argument("--episodes", type=int, default=1000, help="twin episodes per map (default %(default)s)")
    p.add_argument("--hil", action="store_true", help="also run lockstep HIL episodes (pymunk plant, robot controller)")
    p.add_argument("--hil-episodes", type=int, default=50,
                   help="HIL episodes per controller, spread over the maps (default %(default)s)")
    p.add_argument("--profile", action="append", default=None, metavar="ideal|realistic|FILE.toml",
                   help="a robot profile FILE.toml (docs/robot-profile.md): the twin and the HIL sim and robot play "
                        "that robot (the policy must be one it runs: firmware_py.needs; the episodes are the same "
                        "seeded ones as for the built-in robot); ideal|realistic: --hil's plant error "
                        "(sim_bridge/profiles.py: 'realistic' adds wheel slip, a 3 %% encoder scale error and range "
                        "dropouts; default: the sim's default config). Repeatable: one of each")
    p.add_argument("--seed", type=int, default=0, help="scenario seed (default %(default)s)")
    p.add_argument("--policy", default="policies:sector", metavar="FILE",
                   help="the learnt sector policy (.qtab or policies:NAME; default %(default)s)")
    p.add_argument("--controllers", default=None,
                   help="comma-separated subset of learnt,seek,vfh,direct,seek_local,vfh_local,learnt_rules "
                        "(default: the first four, and seek_local and vfh_local when the policy steers on the "
                        "robot's local planner, and learnt_rules, its table with the hand-written recovery rules, "
                        "when it carries a learnt recovery table); a sector-memory policy: learnt,rule")
    p.add_argument("--json", metavar="FILE",
                   help="write the result as JSON (depends only on the seeded episodes: the same on every engine; "
                        "timings and where the jobs ran go to FILE's sibling *.campaign.json)")
    p.add_argument("--png", metavar="FILE", help="comparison figure (default: the JSON path with .png)")
    p.add_argument("--batch", type=int, default=250, metavar="N",
                   help="twin episodes per campaign job (default %(default)s; HIL: N // 50 + 1)")
    add_engine_arguments(p, "episode batches")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from firmware_py.kinds.sector import planner_config
    from firmware_py.policy import PolicyError, load_policy
    from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec
    from ground_station.errors import CliError
    from ground_station.lab.bench.common import report
    from ground_station.lab.campaign.engines import engine_from_args, write_campaign
    from ground_station.lab.nav.controllers import (
        EXTRA_CONTROLLERS,
        NavController,
        kind_controllers,
    )
    from ground_station.lab.nav.episodes import (
        mcnemar_exact,
        paired_time,
        run_job,
        run_twin,
        summarise,
        twin_robot,
    )
    from ground_station.lab.nav.scenario import episodes
    from ground_station.maps import MapError, load_map

    names = tuple(c.strip() for c in (args.controllers or "").split(",") if c.strip())
    if args.controllers is not None and not names:
        raise CliError("--controllers: none named")
    if args.obstacles is None:
        args.obstacles = 0 if args.blocked else 3
    if args.obstacles < 0 or args.movers < 0 or args.episodes < 1 or args.hil_episodes < 1 or args.batch < 1:
        raise CliError("--obstacles/--movers must be >= 0, --episodes/--hil-episodes/--batch >= 1")
    from ground_station.lab.nav.scenario import MOVER_SPEED_MM_S, MoverStyle

    speed = MOVER_SPEED_MM_S
    if args.mover_speed is not None:
        try:
            lo, hi = (float(v) for v in args.mover_speed.split(","))
        except ValueError:
            raise CliError(f"--mover-speed {args.mover_speed!r}: expected LO,HI in mm/s, e.g. 600,1000") from None
        if not 0 < lo <= hi <= 3000:
            raise CliError(f"--mover-speed {args.mover_speed}: expected 0 < LO <= HI <= 3000 mm/s")
        speed = (lo, hi)
    style = MoverStyle(speed=speed, yields=not args.no_yield)
    plant, robot_file = _profiles(args.profile)
    args.profile = plant
    try:
        path = resolve_policy_spec(args.policy)
        pol = load_policy(str(path))
    except (PolicyError, ShippedPolicyError, OSError) as exc:
        raise CliError(f"policy {args.policy}: {exc}") from None
    if robot_file is not None:  # the robot's own check: a policy it would refuse is not benched on it
        from firmware_py.needs import needs_mismatch, needs_of
        from firmware_py.profile import load_profile

        try:
            robot = load_profile(robot_file)
        except ValueError as exc:
            raise CliError(str(exc)) from None
        why = needs_mismatch(needs_of(pol), robot)
        if why:
            raise CliError(f"policy {args.policy} on --profile {robot_file}: {why}")
    try:
        ctrls = list(kind_controllers(pol, names or None))
        if args.controllers is None and planner_config(pol) is not None:
            # the planner with the hand-written seek table: what the learnt table adds
            from firmware_py.kinds.sector.decide import META_KEY as RECOVERY_KEY

            extra = EXTRA_CONTROLLERS if RECOVERY_KEY in pol.metadata else ("seek_local", "vfh_local")
            ctrls += kind_controllers(pol, extra)
    except ValueError as exc:
        raise CliError(f"--controllers: {exc}") from None
    twin_ctrls = [c for c in ctrls if isinstance(c, NavController)]
    if not twin_ctrls and not args.hil:
        raise CliError(f"a {pol.kind} policy has no continuous twin (its trainer's twin is a grid world without "
                       "the scenario's discs and movers): run it with --hil")
    map_names = args.map or list(DEFAULT_MAPS)
    maps = {}
    specs: dict[str, str] = {}  # map name -> the spec that loads it (for campaign workers)
    try:
        for name in map_names:
            gm = load_map(name)
            maps[gm.name] = gm
            specs[gm.name] = name
    except (MapError, OSError) as exc:
        raise CliError(str(exc)) from None
    eps_by_map = {}
    skipped: dict[str, str] = {}
    with tqdm(total=len(maps), desc="scenarios", unit="map") as bar:
        for name, gm in maps.items():
            try:
                if args.blocked is None:
                    eps_by_map[name] = episodes(gm, args.episodes, args.seed, args.obstacles, args.movers,
                                                movers=style)
                else:
                    eps_by_map[name] = _blocked(gm, args, style)
            except MapError as exc:
                if args.blocked is None:
                    raise CliError(str(exc)) from None
                skipped[name] = str(exc)
                tqdm.write(f"--blocked {args.blocked}: skipping {exc}", file=sys.stderr)
            bar.update(1)
    if not eps_by_map:
        raise CliError(f"--blocked {args.blocked}: no map has such an episode ({', '.join(skipped)})")
    if robot_file is not None:  # the same starts, goals and obstacles; waypoints planned around its body
        from ground_station.lab.nav.scenario import for_body

        try:
            eps_by_map = {name: [for_body(maps[name], e, robot.geometry.robot_radius_mm) for e in eps]
                          for name, eps in eps_by_map.items()}
        except MapError as exc:
            raise CliError(f"--profile {robot_file}: {exc}") from None
    for name in skipped:
        del maps[name], specs[name]
    all_eps = [e for eps in eps_by_map.values() for e in eps]
    result: dict = {"scenario": {
        "maps": list(maps), "obstacles": args.obstacles, "movers": args.movers, "seed": args.seed,
        "mover_speed_mm_s": list(style.speed), "movers_yield": style.yields,
        "episodes_per_map": args.episodes,
        "discs_placed_mean": sum(len(e.discs) for e in all_eps) / len(all_eps),
        "movers_placed_mean": sum(len(e.movers) for e in all_eps) / len(all_eps),
        "blocked": args.blocked, "maps_skipped": skipped,
        "definition": "ground_station/lab/nav/scenario.py (detourable discs, movers"
                      + (", blocked passages)" if args.blocked else ")")},
        "policy": str(path), "policy_id": f"0x{pol.policy_id:08x}", "per_map": {}}
    if robot_file is not None:
        result["scenario"]["robot"] = robot_file
        result["scenario"]["waypoints_radius_mm"] = robot.geometry.robot_radius_mm
    rows: list[tuple[str, object]] = []
    base = {"policy": str(path), "maps": specs, **({"robot": robot_file} if robot_file is not None else {})}
    campaign: dict = {}
    with engine_from_args(args) as engine:
        jobs = [{**base, "kind": "twin", "controller": c.name, "map": name, "episodes": eps[i:i + args.batch]}
                for c in twin_ctrls for name, eps in eps_by_map.items() for i in range(0, len(eps), args.batch)]
        out, stats = engine.map(run_job, jobs, desc="twin", unit="batch") if jobs else ([], None)
        if stats is not None:
            campaign["twin"] = stats.as_dict()
        twin_by: dict[str, list[dict]] = {}
        for tc in twin_ctrls:
            twin_rows = []
            for name in maps:
                r = [row for job, res in zip(jobs, out, strict=True)
                     if job["controller"] == tc.name and job["map"] == name for row in res]
                twin_rows += r
                result["per_map"].setdefault(name, {})[tc.name] = summarise(r)
            result[tc.name] = summarise(twin_rows)
            twin_by[tc.name] = twin_rows
        if "learnt" in twin_by:  # the learnt table against each baseline, paired on the same episodes
            result["paired_vs_learnt"] = {
                tc.name: dict(zip(("learnt_only", "baseline_only", "p_exact"),
                                  mcnemar_exact(twin_by["learnt"], twin_by[tc.name]).values(), strict=True))
                for tc in twin_ctrls if tc.name != "learnt"}
            result["paired_time_vs_learnt"] = {tc.name: paired_time(twin_by["learnt"], twin_by[tc.name])
                                               for tc in twin_ctrls if tc.name != "learnt"}
        if args.hil:
            names_list = list(maps)
            per = [args.hil_episodes // len(names_list) + (1 if i < args.hil_episodes % len(names_list) else 0)
                   for i in range(len(names_list))]
            hil_eps = [e for name, k in zip(names_list, per, strict=True) for e in eps_by_map[name][:k]]
            result["hil"] = {"episodes_per_map": dict(zip(names_list, per, strict=True)),
                             "plant": (f"sim_bridge profile '{args.profile}' (sim_bridge/profiles.py)" if args.profile
                                       else "sim_bridge default SimConfig (pymunk, lockstep, sensor noise as qnav-sim)")}
            hb = max(1, args.batch // 50)
            hjobs = [{**base, "kind": "hil", "controller": c.name, "episodes": hil_eps[i:i + hb], "offset": i,
                      "profile": args.profile}
                     for c in ctrls for i in range(0, len(hil_eps), hb)]
            hout, hstats = engine.map(run_job, hjobs, desc="hil", unit="batch")
            campaign["hil"] = {**hstats.as_dict(), "episode_wall_s": {}}
            hil_by: dict[str, list[dict]] = {}
            for c in ctrls:
                hr = [row for job, res in zip(hjobs, hout, strict=True) if job["controller"] == c.name for row in res]
                campaign["hil"]["episode_wall_s"][c.name] = [row.pop("wall_s") for row in hr]
                hil_by[c.name] = hr
                result["hil"][c.name] = summarise(hr)
                for name in names_list:
                    result["hil"].setdefault("per_map", {}).setdefault(name, {})[c.name] = summarise(
                        [row for ep, row in zip(hil_eps, hr, strict=True) if ep.map == name])
                if isinstance(c, NavController):
                    result["hil"].setdefault("twin_same_episodes", {})[c.name] = summarise(
                        run_twin(hil_eps, maps, c, twin_robot(robot_file)))
                result["hil"].setdefault("episodes_detail", {})[c.name] = hr
            if "learnt" in hil_by:
                result["hil"]["paired_vs_learnt"] = {
                    c.name: dict(zip(("learnt_only", "baseline_only", "p_exact"),
                                     mcnemar_exact(hil_by["learnt"], hil_by[c.name]).values(), strict=True))
                    for c in ctrls if c.name != "learnt"}
    blocked = args.blocked is not None
    for c in ctrls:
        if not c.twin:
            rows.append((f"twin {c.name}", f"none: a {pol.kind} policy runs in HIL only (no continuous twin)"))
            continue
        rows.append((f"twin {c.name}", _fmt(result[c.name], blocked)))
    for other, t in result.get("paired_vs_learnt", {}).items():
        rows.append((f"twin learnt vs {other}, paired",
                     f"episodes won only by learnt {t['learnt_only']}, only by {other} {t['baseline_only']}; "
                     f"exact McNemar p = {t['p_exact']:.2g}"))
    for other, t in result.get("paired_time_vs_learnt", {}).items():
        if t["both"]:
            rows.append((f"twin learnt vs {other}, time",
                         f"both reached the goal in {t['both']}: learnt sooner in {t['a_faster']}, {other} in "
                         f"{t['b_faster']}, median learnt - {other} {t['median_diff_s']:+.2f} s; "
                         f"sign test p = {t['p_sign']:.2g}"))
    for name in maps:
        for tc in twin_ctrls:
            rows.append((f"  {name} {tc.name}", _fmt(result["per_map"][name][tc.name], blocked)))
    if args.hil:
        for c in ctrls:
            rows.append((f"hil {c.name}", _fmt(result["hil"][c.name], blocked)))
            for name, per_map in result["hil"]["per_map"].items():
                if per_map[c.name]["episodes"]:
                    rows.append((f"  hil {name} {c.name}", _fmt(per_map[c.name], blocked)))
            if c.twin:
                rows.append((f"  twin, same episodes {c.name}",
                             _fmt(result["hil"]["twin_same_episodes"][c.name], blocked)))
        for other, t in result["hil"].get("paired_vs_learnt", {}).items():
            rows.append((f"hil learnt vs {other}, paired",
                         f"episodes won only by learnt {t['learnt_only']}, only by {other} {t['baseline_only']}; "
                         f"exact McNemar p = {t['p_exact']:.2g}"))
    for part, st in campaign.items():
        rows.append((f"campaign {part}", f"{st['engine']}, {st['workers']} workers on {len(st['nodes'])} node(s): "
                     f"{st['jobs']} jobs, {st['wall_s']:.1f} s wall, speedup over one core "
                     f"{st['speedup_over_one_core']:.2f}x"))
    report("nav", rows, result, args.json)
    write_campaign(args.json, campaign)
    png = args.png or (str(Path(args.json).with_suffix(".png")) if args.json else None)
    if png:
        Path(png).write_bytes(plot(result, [c.name for c in ctrls]))
        print(f"wrote {png}")
    return 0


def _profiles(given: list[str] | None) -> tuple[str | None, str | None]:
    """(plant profile name, robot profile file) of the --profile values (one line, exit 2, otherwise)."""
    from ground_station.errors import CliError

    plant: str | None = None
    robot: str | None = None
    for value in given or []:
        if value in ("ideal", "realistic"):
            if plant is not None:
                raise CliError(f"--profile {value}: a plant profile is given already ({plant})")
            plant = value
        elif value.endswith(".toml") or Path(value).is_file():
            if robot is not None:
                raise CliError(f"--profile {value}: a robot profile is given already ({robot})")
            robot = value
        else:
            raise CliError(f"--profile {value!r}: expected ideal, realistic or a robot profile FILE.toml")
    return plant, robot


def _blocked(gm: GridMap, args: argparse.Namespace, style: MoverStyle) -> list[Episode]:
    """The map's blocked-passage episodes for --blocked (both: the two labels interleaved, so every
    prefix is mixed). Raises MapError when the map has none with a label asked for."""
    from ground_station.lab.nav.scenario import blocked_both, blocked_episodes

    kw = {"k": args.obstacles, "m": args.movers, "movers": style}
    if args.blocked != "both":
        return blocked_episodes(gm, args.episodes, args.seed, args.blocked == "detour", **kw)
    return blocked_both(gm, args.episodes, args.seed, **kw)


def _fmt(s: dict, blocked: bool = False) -> str:
    pr = s["path_ratio_mean"]
    tt = s["time_to_goal_mean_s"]
    lo, hi = s["success_ci95"]
    clo, chi = s["collision_ci95"]
    text = (f"n={s['episodes']:5d} success {s['success_rate']:.3f} [{lo:.3f}, {hi:.3f}] "
            f"collision {s['collision_rate']:.3f} [{clo:.3f}, {chi:.3f}] "
            + (f"path ratio {pr:.3f} " if pr is not None else "path ratio   -   ")
            + (f"time {tt:5.1f} s " if tt is not None else "time   -   ") + f"near-miss {s['near_miss_rate']:.3f}")
    if not blocked:
        return text
    text += f" no-route {s['no_route_rate']:.3f}"
    b = s.get("blocked", {})
    if b.get("detour", {}).get("episodes"):
        d = b["detour"]
        text += f" | detour: n={d['episodes']} success {d['success_rate']:.3f}"
    if b.get("none", {}).get("episodes"):
        d = b["none"]
        nlo, nhi = d["no_route_reported_ci95"]
        text += (f" | none: n={d['episodes']} no-route reported {d['no_route_reported']:.3f} "
                 f"[{nlo:.3f}, {nhi:.3f}]")
    return text


def plot(result: dict, names: list[str]) -> bytes:
    """Grouped bars: success and collision rate per controller, per map and
    overall (twin), plus the HIL figures when present."""
    from ground_station.plotting import png_bytes, pyplot

    plt = pyplot()
    twin = any(c in result for c in names)  # a kind without a continuous twin has HIL figures only
    groups = ([*result["per_map"], "all (twin)"] if twin else []) + (
        [*(f"HIL {m}" for m in result["hil"].get("per_map", {})), "HIL"] if "hil" in result else [])

    def fig_of(g: str, c: str) -> dict:
        if g == "all (twin)":
            return result.get(c, {})
        if g == "HIL":
            return result["hil"][c]
        if g.startswith("HIL "):
            return result["hil"]["per_map"][g[4:]][c]
        return result["per_map"][g].get(c, {})

    fig, axes = plt.subplots(2, 1, figsize=(max(7, 1.6 * len(groups)), 6), dpi=100, sharex=True)
    width = 0.8 / len(names)
    for ax, key, title in ((axes[0], "success_rate", "success"), (axes[1], "collision_rate", "collision")):
        for j, c in enumerate(names):
            xs = [i + (j - (len(names) - 1) / 2) * width for i in range(len(groups))]
            ax.bar(xs, [fig_of(g, c).get(key, 0.0) for g in groups], width, label=c)
        ax.set_ylabel(f"{title} rate")
        ax.set_ylim(0, 1.05)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(ncol=len(names), fontsize=8)
    axes[1].set_xticks(range(len(groups)))
    axes[1].set_xticklabels(groups, rotation=20, fontsize=8)
    sc = result["scenario"]
    kind = f"blocked passages ({sc['blocked']}) + " if sc.get("blocked") else ""
    axes[0].set_title(f"qnav bench nav: {kind}{sc['obstacles']} static + {sc['movers']} moving obstacles, "
                      f"seed {sc['seed']}, {sc['episodes_per_map']} twin episodes/map")
    fig.tight_layout()
    return png_bytes(fig)
