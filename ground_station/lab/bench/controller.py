"""`qnav bench controller`: the robot control loop's latency, CPU and memory.

Runs the real processes at the real rate: a python-can-remote hub on
127.0.0.1, `qnav-sim --realtime` (paced at 20 Hz sim ticks on paper10) and
`qnav-robot --sim-clock` driving the shipped cell policy to a target. The
robot process measures, per tick, the wall time from the tick's last input
frame (the SimTick) to its command handed to the bus, and reports its CPU
time and resident memory at exit.

It runs twice: with normal scheduling, and with the robot's ticking thread
at SCHED_FIFO (`qnav-robot --rt-priority`, how firmware runs its loop; on a
shared, loaded machine the difference is the OS preempting the tick).

Baselines measured in the same run: the control period (the deadline the
loop must meet) and `Controller.step` alone in this process on recorded-like
inputs (the decision's pure compute, no bus, no threads).

Then the step's compute with the policy's own work in it (issue 29):
`Controller.step` thread CPU time per tick on the in-process lockstep rig
(pymunk plant, the robot's localiser tracking on the policy's map), for
the cell policy on paper10 trips and for `--nav-policy` (default the shipped
sector policy, its local planner on) on the navigation scenario with
`--obstacles` discs and `--movers` movers over `--episodes` episodes, the
cell policy over as many trips or more, until it has as many ticks (p99s
from samples of one size): p50 / p99 / max side by side, and the ratio of
the p99s; beside them the same policy with its planner off (no obstacle
layer, no plan read) on the scenario's trips without discs or movers, as
many ticks again (without its planner the robot stalls at a disc, and a
standing robot's localiser idles): the baseline for what the planner costs
the tick. The local
planner's search is not in those figures: it runs between ticks
(firmware_py.background); its CPU per tick and its longest job are
reported beside them.

Then, unless `--no-load`, the link isolation (issue 13): the robot with its
MAVLink node on UDP (`ground_station.lab.faults.link_faults.load_run`), once
quiet (no ground station: the baseline) and once loaded (three ground
stations, 10 Hz telemetry, uploads back to back, and the floods of
`ground_station.lab.faults.floods`: 600 PARAM_SET, 300 PARAM_REQUEST_LIST, 150
CalcFileCRC32 of a 6 MB file, in turn). Reported on the wall clock for
each: tick (SimTick arrival -> command), compute (step start -> command),
lag against the pace, periods lost; the loaded/quiet ratio of the p99s.
And in this process, the interpreter-lock wait behind the thread/process
choice: how late a thread waking every 10 ms runs alone, and beside a
thread running pure Python at CPython's default switch interval (5 ms) and
at qnav-robot's (0.5 ms).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from firmware_py.policy import Policy
    from ground_station.lab.nav.controllers import BenchController


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("controller", help="control loop tick latency (p50/p99/max vs the period), CPU, RSS",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=20.0, help="wall seconds of paced (real-time) HIL")
    p.add_argument("--policy", default="policies:paper10_cell", metavar="FILE",
                   help="a .qtab file or policies:NAME (default %(default)s, shipped)")
    p.add_argument("--goal-cell", default="9,0", metavar="COL,ROW", help="target cell on paper10 (default B)")
    p.add_argument("--start", default="0.25,0.25,0", metavar="X,Y,DEG")
    p.add_argument("--rt-priority", type=int, default=10, metavar="N",
                   help="also run with the robot's ticking thread SCHED_FIFO at N (0: skip)")
    p.add_argument("--no-load", dest="load", action="store_false",
                   help="skip the quiet-vs-loaded MAVLink runs")
    p.add_argument("--gil-switch-us", type=int, default=None, metavar="US",
                   help="qnav-robot --gil-switch-us for the quiet and loaded runs (default: the robot's)")
    p.add_argument("--nav-policy", default="policies:sector", metavar="FILE",
                   help="the policy whose step runs with obstacles (default %(default)s)")
    p.add_argument("--obstacles", type=int, default=3, metavar="K", help="static discs per episode (default 3)")
    p.add_argument("--movers", type=int, default=2, metavar="M", help="moving discs per episode (default 2)")
    p.add_argument("--episodes", type=int, default=4, metavar="N",
                   help="lockstep episodes per policy for the step compute (default 4; 0: skip)")
    p.add_argument("--json", metavar="FILE", help="write the result as JSON")
    p.set_defaults(func=run)


def _pcts(values: list[float]) -> dict[str, float]:
    from ground_station.lab.bench.hil import _pct

    v = sorted(values)
    if not v:
        return {"p50_us": 0.0, "p99_us": 0.0, "max_us": 0.0, "ticks": 0}
    return {"p50_us": _pct(v, 0.5), "p99_us": _pct(v, 0.99), "max_us": v[-1], "ticks": len(v)}


@dataclass
class PlannerOff:
    """A bench controller's policy with its local planner removed (map and localiser kept)."""

    inner: BenchController
    name: str = "planner off"
    twin: bool = False

    @property
    def guidance(self) -> str:
        return self.inner.guidance

    @property
    def local(self) -> None:
        return None

    def policy(self, map_name: str = "") -> Policy:
        return replace(self.inner.policy(map_name), kind_config=None)


BASELINE_TRIPS = 10  # the baselines' trips are at most this many times the sector side's episodes


def _trips_until(want_ticks: int, least: int, most: int,
                 trip: Callable[[int], tuple[list[float], Any]]) -> tuple[list[float], list[Any]]:
    """`trip(i)` -> (its per-tick CPU, its result) for i = 0, 1, ...: at least `least` trips, then on
    until the ticks number `want_ticks`, at most `most` trips. (pooled CPU, the results)"""
    cpu: list[float] = []
    results: list[Any] = []
    while len(results) < least or (len(cpu) < want_ticks and len(results) < most):
        ticks, result = trip(len(results))
        cpu += ticks
        results.append(result)
    return cpu, results


def step_compute(nav_policy: str, episodes: int, obstacles: int, movers: int, seed: int = 0) -> dict:
    """Controller.step CPU per tick on the lockstep rig: the cell policy on paper10
    far trips vs `nav_policy` on scenario episodes with obstacles (module doc)."""
    import random

    from firmware_py.policy import load_policy
    from ground_station.lab.nav.controllers import standard_controllers
    from ground_station.lab.nav.episodes import run_hil
    from ground_station.lab.nav.scenario import episodes as nav_episodes
    from ground_station.lab.rigs.lockstep import cell_policy, far_trip, run_episode
    from ground_station.maps import load_map
    from ground_station.maps.planner import guidance_from_metadata

    gm = load_map("paper10")
    pol = load_policy(nav_policy)
    ctrl = standard_controllers(pol, ("learnt",))[0]
    eps = nav_episodes(gm, episodes, seed, obstacles, movers, plan_kw=guidance_from_metadata(pol.metadata))
    rows = run_hil(eps, {gm.name: gm}, ctrl, step_cpu=True)
    nav_cpu = [v for r in rows for v in r["step_cpu_us"]]
    # The baselines run trips until they have as many ticks as the sector side (at most
    # BASELINE_TRIPS x `episodes`): p99s from samples of one size (4 cell trips gave ~1,800
    # ticks to the sector side's ~4,800, and the ratio of the p99s swung with the smaller one).
    cap = BASELINE_TRIPS * max(episodes, 1)
    cell = cell_policy()
    rng = random.Random(seed)

    def cell_trip(i: int) -> tuple[list[float], None]:
        start, goal = far_trip(gm, cell, rng)
        return run_episode(gm.occ, cell, start, [goal], max_sim_s=60.0, seed=seed + i).step_cpu_us, None

    cell_cpu, cell_runs = _trips_until(len(nav_cpu), episodes, cap, cell_trip)
    # The step without the planner: the same policy, map and localiser, its local planner
    # off (no obstacle layer, no plan to read), on the scenario's trips without discs or
    # movers: without a planner the robot stalls at the first disc, and a standing robot's
    # localiser has nothing to do, which would flatter the ratio.
    bare = PlannerOff(ctrl)
    clear = nav_episodes(gm, cap, seed, 0, 0, plan_kw=guidance_from_metadata(pol.metadata))  # prefixes agree

    def bare_trip(i: int) -> tuple[list[float], dict]:
        (row,) = run_hil([clear[i]], {gm.name: gm}, bare, step_cpu=True)
        return row["step_cpu_us"], row

    bare_cpu, bare_rows = _trips_until(len(nav_cpu), episodes, cap, bare_trip)
    cell_p, nav_p, bare_p = _pcts(cell_cpu), _pcts(nav_cpu), _pcts(bare_cpu)
    off_tick = {"background_cpu_us_per_tick": sum(r["background_cpu_us"] for r in rows) / max(len(nav_cpu), 1),
                "background_runs": sum(r["background_runs"] for r in rows),
                "background_max_us": max((r["background_max_us"] for r in rows), default=0.0)}
    return {"cell": {"policy": "policies:paper10_cell", "trips": len(cell_runs), **cell_p},
            "nav": {"policy": nav_policy, "obstacles": obstacles, "movers": movers,
                    "outcomes": [r["outcome"] for r in rows], **nav_p, **off_tick},
            "nav_planner_off": {"policy": nav_policy, "outcomes": [r["outcome"] for r in bare_rows], **bare_p},
            "episodes": episodes, "seed": seed, "map": gm.name, "localiser": "on (the policies' map)",
            "nav_over_cell_p99": nav_p["p99_us"] / max(cell_p["p99_us"], 1e-9),
            "planner_on_over_off_p99": nav_p["p99_us"] / max(bare_p["p99_us"], 1e-9)}


def core_step_baseline(policy_path: str, n: int = 2000) -> dict:
    """`Controller.step` alone: p50/p99 µs over n ticks of a kinematic drive."""
    import math

    from firmware_py import robot_spec
    from firmware_py.control.controller import Controller
    from firmware_py.control.io import Inputs
    from firmware_py.policy import load_policy

    pol = load_policy(policy_path)
    ctrl = Controller(policy=pol, start_pose_mm=(250, 250, 0))
    per_mm = robot_spec.ENCODER_TICKS_PER_REV / (2 * math.pi * robot_spec.WHEEL_RADIUS_MM)
    left = right = 0.0
    times = []
    goal = pol.goals[1] if pol.kind == "cell" and len(pol.goals) > 1 else (9, 0)
    gx, gy = robot_spec.cell_center_mm(*goal, 10)
    for k in range(n):
        t = k * robot_spec.CONTROL_PERIOD_US
        inp = Inputs(ranges_mm=[1500] * robot_spec.SENSOR_COUNT, range_status=[0] * robot_spec.SENSOR_COUNT,
                     ranges_us=[t, t], enc_left=round(left * per_mm), enc_right=round(right * per_mm),
                     enc_us=t, bumper_us=t, driver_us=t)
        t0 = time.perf_counter_ns()
        out = ctrl.step(inp, t)
        times.append(time.perf_counter_ns() - t0)
        if k == 1:
            ctrl.arm()
            ctrl.go_to(gx, gy)
        if out.motor is not None:  # ideal wheels: enough to keep the decision path busy
            left += out.motor.left_mm_s * robot_spec.CONTROL_PERIOD_US / 1e6
            right += out.motor.right_mm_s * robot_spec.CONTROL_PERIOD_US / 1e6
    times.sort()
    return {"core_step_p50_us": times[len(times) // 2] / 1000,
            "core_step_p99_us": times[int(0.99 * (len(times) - 1))] / 1000}


def paced_run(args: argparse.Namespace, rt_priority: int | None) -> dict:
    """One paced HIL run (hub + qnav-sim --realtime + qnav-robot); the robot's stats."""
    import subprocess

    from firmware_py import robot_spec
    from ground_station.canhub import CanHub
    from ground_station.errors import CliError
    from ground_station.processes import ChildProcess, qnav_robot, qnav_sim

    rt = [] if rt_priority is None else ["--rt-priority", str(rt_priority)]
    with tempfile.TemporaryDirectory() as tmp, CanHub("bench") as hub:
        stats_path = Path(tmp) / "robot.json"
        sim = ChildProcess(qnav_sim("--map", "paper10", "--can", hub.spec, "--realtime",
                                    "--duration", str(args.seconds), "--start", args.start, "-q"),
                           Path(tmp) / "sim.log")
        rob = ChildProcess(qnav_robot("--can", hub.spec, "--sim-clock", "--policy", args.policy,
                                      "--start", args.start, "--goal-cell", args.goal_cell, *rt,
                                      "--duration", str(args.seconds - robot_spec.CONTROL_PERIOD_US / 1e6),
                                      "--stats-json", str(stats_path), "--mavlink", "none", "-q"),
                           Path(tmp) / "robot.log")
        with sim, rob:
            try:
                sim.wait(args.seconds + 60)
                rob.wait(30)
            except subprocess.TimeoutExpired:
                pass  # stopped on leaving the block; reported below
        if sim.returncode != 0 or not stats_path.is_file():
            raise CliError(f"HIL run failed: sim rc {sim.returncode} {sim.log_text().strip()[-200:]!r}; "
                           f"robot rc {rob.returncode} {rob.log_text().strip()[-200:]!r}")
        return json.loads(stats_path.read_text())


def gil_wait(switch_us: int | None, busy: bool, seconds: float = 1.5, period_s: float = 0.01) -> dict:
    """How late a thread that wakes every `period_s` runs (p50/p99/max µs), with or
    without a second thread running pure Python (a link handler) at the given
    switch interval: the interpreter-lock wait a tick can see beside the link thread."""
    import sys
    import threading

    old = sys.getswitchinterval()
    if switch_us is not None:
        sys.setswitchinterval(switch_us / 1e6)
    stop = threading.Event()

    def spin() -> None:
        x = 0
        while not stop.is_set():
            for i in range(1000):
                x += i * i

    spinner = threading.Thread(target=spin, daemon=True)
    if busy:
        spinner.start()
    late = []
    try:
        t_next = time.perf_counter() + period_s
        t_end = time.perf_counter() + seconds
        while t_next < t_end:
            time.sleep(max(0.0, t_next - time.perf_counter()))
            late.append(time.perf_counter() - t_next)
            t_next += period_s
    finally:
        stop.set()
        if busy:
            spinner.join()
        sys.setswitchinterval(old)
    late.sort()
    n = len(late) - 1
    return {"p50_us": late[n // 2] * 1e6, "p99_us": late[int(0.99 * n)] * 1e6, "max_us": late[-1] * 1e6}


LOAD_FIGURES = ("tick_p50_us", "tick_p99_us", "tick_max_us", "compute_p50_us", "compute_p99_us", "compute_max_us",
                "lag_p99_us", "lag_max_us", "wall_overruns", "overruns", "ticks", "sim_ticks", "cpu_percent")


def load_variants(args: argparse.Namespace) -> dict:
    """Quiet and loaded runs of the robot with MAVLink (module doc); both dicts + ratios."""
    from ground_station.errors import CliError
    from ground_station.lab.faults.link_faults import load_run

    extra = () if args.gil_switch_us is None else ("--gil-switch-us", str(args.gil_switch_us))
    out: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, clients in (("quiet", False), ("loaded", True)):
            r = load_run(args.seconds, 77 if clients else 76, Path(tmp), clients_on=clients, floods=clients,
                         extra_args=extra)
            if "tick_p99_us" not in r:
                raise CliError(f"{name} run failed: {'; '.join(r['problems'])}")
            out[name] = {k: r.get(k) for k in (*LOAD_FIGURES, "problems", "floods_done", "uploads", "param_lists",
                                               "link_frames", "link_budget_exhausted", "switch_interval_us")}
    for k in ("tick_p99_us", "compute_p99_us"):
        q = out["quiet"][k]
        out[f"{k}_ratio"] = out["loaded"][k] / q if q else None
    return out


KEYS = ("tick_p50_us", "tick_p99_us", "tick_max_us", "ticks", "overruns", "cpu_percent", "rss_mb")


def run(args: argparse.Namespace) -> int:
    from ground_station.errors import CliError
    from ground_station.lab.bench.common import report

    if not args.seconds > 0:
        raise CliError(f"--seconds must be positive, got {args.seconds:g}")
    from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec

    try:
        args.policy = str(resolve_policy_spec(args.policy))
    except ShippedPolicyError as exc:
        raise CliError(f"policy {args.policy}: {exc}") from None
    if not Path(args.policy).is_file():
        raise CliError(f"policy {args.policy} not found")
    variants = [("normal", None)]
    if args.rt_priority:
        variants.append((f"fifo{args.rt_priority}", args.rt_priority))
    base = core_step_baseline(args.policy)
    result: dict = {"period_us": 0, **base, "variants": {}}
    rows: list[tuple[str, object]] = []
    for name, prio in variants:
        stats = paced_run(args, prio)
        period = stats["period_us"]
        result["period_us"] = period
        v = {k: stats[k] for k in KEYS}
        v.update(p99_over_period=stats["tick_p99_us"] / period,
                 p50_over_core_step=stats["tick_p50_us"] / base["core_step_p50_us"],
                 rt_active=stats.get("rt_active", False), robot_result=stats["result"])
        result["variants"][name] = v
        if name == "normal":
            result.update({k: v[k] for k in KEYS})  # the headline figures: default scheduling
        label = "normal scheduling" if prio is None else (
            f"SCHED_FIFO {prio}" + ("" if v["rt_active"] else " (NOT granted)"))
        rows += [(f"[{label}] tick_p50_us", v["tick_p50_us"]),
                 (f"[{label}] tick_p99_us", v["tick_p99_us"]),
                 (f"[{label}] tick_max_us", v["tick_max_us"]),
                 (f"[{label}] tick_p99 / period", v["p99_over_period"]),
                 (f"[{label}] tick_p50 / core_step_p50", v["p50_over_core_step"]),
                 (f"[{label}] ticks / overruns", f"{v['ticks']} / {v['overruns']}"),
                 (f"[{label}] cpu_percent (1 core = 100)", v["cpu_percent"]),
                 (f"[{label}] rss_mb", v["rss_mb"])]
    gil = {"no second thread": gil_wait(None, False), "busy thread, CPython default 5000 us": gil_wait(5000, True),
           "busy thread, 500 us (qnav-robot default)": gil_wait(500, True)}
    result["gil_wait"] = gil
    rows += [(f"[GIL wait] {k}: wake-up late p50 / p99 / max us",
              f"{v['p50_us']:.0f} / {v['p99_us']:.0f} / {v['max_us']:.0f}") for k, v in gil.items()]
    if args.episodes > 0:
        from firmware_py.shipped_policies import resolve_policy_spec as _resolve

        sc = step_compute(str(_resolve(args.nav_policy)), args.episodes, args.obstacles, args.movers)
        result["step_compute"] = sc
        scene = f"{Path(args.nav_policy).name} + {args.obstacles} discs + {args.movers} movers"
        for key, label in (("cell", "cell policy, paper10 trips"), ("nav", scene),
                           ("nav_planner_off", f"{Path(args.nav_policy).name}, planner off, no discs or movers")):
            v = sc[key]
            rows.append((f"[step compute, lockstep, localiser on] {label}: p50 / p99 / max us ({v['ticks']} ticks)",
                         f"{v['p50_us']:.0f} / {v['p99_us']:.0f} / {v['max_us']:.0f}"))
        rows.append(("[step compute] p99 with obstacles / cell p99", round(sc["nav_over_cell_p99"], 2)))
        rows.append(("[step compute] p99 planner on / planner off",
                     round(sc["planner_on_over_off_p99"], 2)))
        v = sc["nav"]
        rows.append(("[off the tick] planner search CPU per tick mean / longest job us (jobs)",
                     f"{v['background_cpu_us_per_tick']:.0f} / {v['background_max_us']:.0f} ({v['background_runs']})"))
    if args.load:
        lv = load_variants(args)
        result["load"] = lv
        for name in ("quiet", "loaded"):
            v = lv[name]
            label = ("MAVLink quiet (baseline)" if name == "quiet" else
                     "MAVLink loaded: 3 GCS + uploads + floods")
            rows += [(f"[{label}] tick p50 / p99 / max us",
                      f"{v['tick_p50_us']:.0f} / {v['tick_p99_us']:.0f} / {v['tick_max_us']:.0f}"),
                     (f"[{label}] compute p50 / p99 / max us",
                      f"{v['compute_p50_us']:.0f} / {v['compute_p99_us']:.0f} / {v['compute_max_us']:.0f}"),
                     (f"[{label}] lag p99 / max us", f"{v['lag_p99_us']:.0f} / {v['lag_max_us']:.0f}"),
                     (f"[{label}] ticks / SimTicks / wall periods lost",
                      f"{v['ticks']} / {v['sim_ticks']} / {v['wall_overruns']}")]
        rows += [("loaded / quiet tick_p99", lv["tick_p99_us_ratio"]),
                 ("loaded / quiet compute_p99", lv["compute_p99_us_ratio"]),
                 ("floods done (loaded run)", lv["loaded"].get("floods_done"))]
    rows = [("period_us (deadline)", result["period_us"]),
            ("core_step_p50_us (baseline: step alone)", base["core_step_p50_us"])] + rows
    report("controller", rows, result, args.json)
    return 0
