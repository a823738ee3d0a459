"""`qnav-robot`: run the robot controller on a CAN bus.

    qnav-robot --can remote:ws://127.0.0.1:PORT/ --policy policies:sector \\
               --lockstep --start 0.75,0.75,90 --goal 4.75,4.75 --exit-when-done

Goals come from the command line until a MAVLink node is attached: with
`--goal` (repeatable: a mission) the robot arms as soon as its inputs are
fresh and drives the goals in order. Without a goal it idles in STANDBY.

Extension hook (the MAVLink shell): append an object to `EXTENSIONS` with
`add_arguments(parser)` and `attach(node, args) -> stop_callable | None`.
`node.controller` is the `vehicle.VehicleControl`; `node.after_tick` takes
per-tick callbacks (they run in the ticking thread and must not wait: the
MAVLink extension runs its link in its own thread). Both run before the node
starts. An extension with a `stats()` method adds its counters to
`--stats-json`.
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import signal
import sys
import time
from typing import TYPE_CHECKING, Any

from firmware_py import kinds, robot_spec
from firmware_py.atomic import atomic_write
from firmware_py.clock import SimClock, WallClock
from firmware_py.control.controller import Controller
from firmware_py.control.goals import GoalRunner
from firmware_py.control.node import RobotNode
from firmware_py.helpformat import DefaultsHelpFormatter
from firmware_py.mavlink.extension import MavlinkExtension
from firmware_py.plugins import EXIT_FAULT, EXIT_OK, EXIT_TIMEOUT, EXIT_USAGE, Extension, UsageError
from firmware_py.stackdump import dump_stacks_on_sigusr1
from firmware_py.vehicle import VehicleConfig

if TYPE_CHECKING:  # loaded lazily (see _load_policy)
    from firmware_py.policy import Policy

EXTENSIONS: list[Extension] = [MavlinkExtension()]


def _floats(text: str, n_min: int, n_max: int, what: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise UsageError(f"{what} {text!r}: expected numbers separated by commas") from None
    if not n_min <= len(vals) <= n_max:
        raise UsageError(f"{what} {text!r}: expected {n_min}{'-' + str(n_max) if n_max > n_min else ''} values")
    return vals


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="qnav-robot", description=__doc__,
                                formatter_class=DefaultsHelpFormatter)
    p.add_argument("--can", metavar="SPEC", default=None,
                   help="CAN bus: virtual:NAME, remote:ws://127.0.0.1:PORT/, socketcan:CH, slcan:DEV "
                        "(default: python-can's own configuration)")
    p.add_argument("--policy", metavar="FILE", help=".qtab policy to run, or policies:NAME for a shipped one "
                                                    "(default: the active one in --storage)")
    p.add_argument("--localiser", choices=("on", "off"), default="on",
                   help="Monte Carlo localisation on the map the policy carries (on), or dead reckoning alone "
                        "(off: what the ideal sim plant, with exact encoders, needs; docs/architecture.md)")
    p.add_argument("--storage", metavar="DIR", help="the robot's file store (active/last-good policies, parameters; "
                   "default: none: parameters in memory only and no MAVLink FTP uploads)")
    clk = p.add_mutually_exclusive_group()
    clk.add_argument("--lockstep", action="store_true",
                     help="HIL lockstep: step on every SimTick and answer it (the sim waits)")
    clk.add_argument("--sim-clock", action="store_true",
                     help="paced HIL: run on sim time from SimTick frames, do not answer ticks")
    p.add_argument("--rate", type=int, default=robot_spec.CONTROL_RATE_HZ, metavar="HZ",
                   help=f"control rate on the wall or sim clock ({robot_spec.CONTROL_RATE_MIN_HZ}.."
                        f"{robot_spec.CONTROL_RATE_MAX_HZ}, default {robot_spec.CONTROL_RATE_HZ}; in lockstep the "
                        "sim's tick sets the pace); a policy must have been trained for this period")
    p.add_argument("--start", metavar="X,Y[,DEG]", help="start pose in metres (world frame) and heading in degrees CCW from east")
    p.add_argument("--start-cell", metavar="COL,ROW[,DEG]", help="start pose at a map cell's centre")
    p.add_argument("--goal", action="append", default=[], metavar="X,Y",
                   help="goal in metres; repeat for a mission driven in order")
    p.add_argument("--goal-cell", action="append", default=[], metavar="COL,ROW",
                   help="goal at a map cell's centre; repeatable")
    p.add_argument("--profile", metavar="FILE.toml",
                   help="robot profile: geometry and the drive/sensor backends (docs/robot-profile.md; "
                        "examples in firmware_py/profiles/); default: the built-in robot on qnav's frames")
    p.add_argument("--map", metavar="FILE.map",
                   help="the robot's own map (MovingAI .map, --cell-size cells): a policy carrying another map "
                        "is refused, naming both (qnav sitl passes the map it simulates)")
    p.add_argument("--map-height", type=int, metavar="H",
                   help="map rows, for --start-cell/--goal-cell with a sector policy (cell policies know it)")
    p.add_argument("--cell-size", type=float, metavar="M", help="cell size in metres (default: the policy's, else 0.5)")
    p.add_argument("--sensor-timeout-ms", type=int, default=VehicleConfig.sensor_timeout_ms, metavar="MS",
                   help="a sensor input older than this is stale: the motors stop")
    p.add_argument("--motor-timeout-ms", type=int, default=VehicleConfig.motor_timeout_ms, metavar="MS",
                   help="the motor driver's command watchdog the robot configures")
    check = p.add_argument_group("bring-up and deployment (docs/deploy.md)")
    check.add_argument("--print-unit", action="store_true",
                       help="print the systemd unit shipped with the package (Type=notify, watchdog, restart) and exit")
    check.add_argument("--check", action="store_true",
                       help="list which boards answer on --can (drive, range sensors, bumper, battery) with their "
                            "state and errors, then exit: 0 everything needed answered, 1 not")
    check.add_argument("--check-motors", action="store_true",
                       help="with --check: also turn each wheel alone, slowly (the robot turns ~45 deg round the "
                            "other wheel), and report whether it drove the way the profile's sign says")
    check.add_argument("--check-listen", type=float, default=2.0, metavar="S",
                       help="with --check: seconds to listen for the boards")
    p.add_argument("--exit-when-done", action="store_true",
                   help="exit 0 when the goals are reached, 3 on FAULT")
    p.add_argument("--duration", type=float, metavar="S",
                   help="stop after S seconds (sim time with --lockstep/--sim-clock); exit 4 if goals are pending")
    p.add_argument("--rt-priority", type=int, metavar="N",
                   help="run the ticking threads SCHED_FIFO at priority N (Linux, needs privilege; "
                        "falls back to normal scheduling with a warning)")
    p.add_argument("--gil-switch-us", type=int, default=500, metavar="US",
                   help="CPython's thread switch interval while the MAVLink link thread runs (default "
                        "%(default)s; 0 keeps CPython's 5000): how long a tick can wait for the interpreter "
                        "lock held by the link thread")
    p.add_argument("--stats-json", metavar="FILE", help="write loop statistics and the final state as JSON at exit")
    p.add_argument("-q", "--quiet", action="store_true", help="only warnings (transitions are logged by default)")
    for ext in EXTENSIONS:
        ext.add_arguments(p)
    return p


def _policy_cell_mm(args: argparse.Namespace, policy: Policy | None) -> int:
    """The robot's map cell size: --cell-size, else a cell policy's, else the default."""
    if args.cell_size:
        return round(float(args.cell_size) * 1000)
    cell_mm = kinds.of_policy(policy).robot_cell_mm(policy) if policy is not None else None
    return robot_spec.DEFAULT_CELL_SIZE_MM if cell_mm is None else cell_mm  # a kind that steps on its grid


def _fits(args: argparse.Namespace, policy: Policy) -> str:
    """Why `policy` does not fit this command line's robot ('' if it does)."""
    from firmware_py.policy import config_mismatch
    why = config_mismatch(policy, robot_spec.control_period_us(args.rate), _policy_cell_mm(args, policy),
                          getattr(args, "robot_map", None), getattr(args, "robot_profile", None))
    height = policy.map_geometry.height
    fixed = kinds.of_policy(policy).fixed_geometry(policy.encoder, policy.cell_mm)  # a cell policy's own grid
    if not why and args.map_height and fixed is not None and height != args.map_height:
        why = f"policy grid height {height} != robot --map-height {args.map_height}"
    if not why and policy.map_grid is not None and getattr(args, "localiser", "on") == "on":
        from firmware_py.control.localiser import LocaliserConfig, likelihood_field

        cfg = LocaliserConfig()
        try:  # built now (and cached for the controller): a map the robot cannot hold is refused, not a crash
            likelihood_field(policy.map_grid, cfg.field_res_mm, cfg.sigma_hit_mm, cfg.z_hit, cfg.z_floor,
                             cfg.max_field_mm)
        except MemoryError:
            why = "its map's localiser field does not fit in memory"
    return why


def _load_policy(args: argparse.Namespace) -> Policy | None:
    """The --policy file, else the first boot candidate in --storage that loads
    and fits the robot's control period and map (policy.config_mismatch)."""
    from firmware_py.policy import PolicyError, load_policy
    from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec
    if args.policy:
        try:
            policy = load_policy(resolve_policy_spec(args.policy))
        except (PolicyError, ShippedPolicyError) as exc:
            raise UsageError(f"policy {args.policy}: {exc}") from None
        why = _fits(args, policy)
        if why:
            raise UsageError(f"policy {args.policy}: {why}")
        return policy
    if args.storage:
        from firmware_py.storage import Storage, boot_policy_candidates
        for path in boot_policy_candidates(Storage(args.storage)):
            try:
                policy = load_policy(path)
            except PolicyError as exc:
                logging.getLogger("qnav.robot").warning("boot policy %s rejected: %s", path, exc)
                continue
            why = _fits(args, policy)
            if not why:
                return policy
            logging.getLogger("qnav.robot").warning("boot policy %s rejected: %s", path, why)
    return None


def _rss_mb() -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _check(args: argparse.Namespace) -> int:
    """qnav-robot --check: the bring-up report (firmware_py/bringup.py); exit 0 all there, 1 not."""
    from firmware_py.bringup import run_check
    from firmware_py.canbus import CanSpecError, open_bus
    from firmware_py.profile import DEFAULT

    if not 0.2 <= args.check_listen <= 60:
        raise UsageError(f"--check-listen {args.check_listen:g}: expected 0.2..60 s")
    try:
        bus = open_bus(args.can)
    except CanSpecError as exc:
        raise UsageError(str(exc)) from None
    try:
        rep = run_check(bus, args.robot_profile or DEFAULT, listen_s=args.check_listen, spin=args.check_motors)
    except ValueError as exc:  # a backend this install cannot run (the dronecan extra missing)
        raise UsageError(f"--profile {args.profile}: {exc}") from None
    finally:
        bus.shutdown()
    for line in rep.lines:
        print(line)
    if rep.problems:
        print(f"qnav-robot --check: {len(rep.problems)} problem(s): {rep.problems[0]}", file=sys.stderr)
        return 1
    print("qnav-robot --check: every board answered" + (", both wheels drive forward" if args.check_motors else ""))
    return 0


def run(args: argparse.Namespace) -> int:
    """`_run` with the robot's own log around it (from before boot, so the boot's map and policy lines
    go in, to after the last line, whatever ends the run)."""
    onboard = None
    if args.storage and not args.check and not args.print_unit:
        from firmware_py.onboard_log import OnboardLog

        try:
            onboard = OnboardLog(args.storage).start()
        except OSError as exc:  # a read-only or full disk: the robot runs without its log
            logging.getLogger("qnav.robot").warning("onboard log not written: %s", exc)
    try:
        return _run(args, onboard)
    finally:
        if onboard is not None:
            onboard.stop()


def _run(args: argparse.Namespace, onboard: Any) -> int:
    from firmware_py.canbus import CanSpecError, open_bus

    why = robot_spec.control_rate_error(args.rate)
    if why:
        raise UsageError(f"--rate {args.rate}: {why}")
    args.robot_profile = None
    if args.profile:
        from firmware_py.profile import ProfileError, load_profile

        try:
            args.robot_profile = load_profile(args.profile)
        except ProfileError as exc:
            raise UsageError(f"--profile {exc}") from None
    if args.print_unit:
        from importlib import resources

        print(resources.files("firmware_py").joinpath("deploy/qnav-robot.service").read_text(encoding="utf-8"), end="")
        return EXIT_OK
    if args.check_motors and not args.check:
        raise UsageError("--check-motors goes with --check")
    if args.check:
        return _check(args)
    args.robot_map = None
    if args.map:
        from firmware_py.mapdata import MapDataError, grid_from_map_file

        try:
            args.robot_map = grid_from_map_file(args.map, _policy_cell_mm(args, None))  # --cell-size or the default
        except MapDataError as exc:
            raise UsageError(f"--map {exc}") from None
    policy = _load_policy(args)
    cell_mm = _policy_cell_mm(args, policy)
    fixed = kinds.of_policy(policy).fixed_geometry(policy.encoder, policy.cell_mm) if policy is not None else None
    height = args.map_height or (fixed[2] if fixed is not None else None)

    def cell_point(text: str, what: str, with_heading: bool) -> tuple[int, int, int]:
        if height is None:
            raise UsageError(f"{what} needs --map-height (or a cell policy)")
        v = _floats(text, 2, 3 if with_heading else 2, what)
        x, y = robot_spec.cell_center_mm(int(v[0]), int(v[1]), height, cell_mm)
        return x, y, round(v[2] * 3141.5927 / 180) if len(v) > 2 else 0

    start = (0, 0, 0)
    if args.start and args.start_cell:
        raise UsageError("give --start or --start-cell, not both")
    if args.start:
        v = _floats(args.start, 2, 3, "--start")
        start = (round(v[0] * 1000), round(v[1] * 1000), round(v[2] * 3141.5927 / 180) if len(v) > 2 else 0)
    elif args.start_cell:
        start = cell_point(args.start_cell, "--start-cell", True)
    goals = [(round(x * 1000), round(y * 1000)) for x, y in (_floats(g, 2, 2, "--goal") for g in args.goal)]
    goals += [cell_point(g, "--goal-cell", False)[:2] for g in args.goal_cell]

    prof = args.robot_profile
    cfg = VehicleConfig(control_rate_hz=args.rate, sensor_timeout_ms=args.sensor_timeout_ms,
                        motor_timeout_ms=args.motor_timeout_ms, cell_size_mm=cell_mm,
                        max_wheel_speed_mm_s=prof.drive.max_speed_mm_s if prof else robot_spec.MAX_WHEEL_SPEED_MM_S)
    sim = args.lockstep or args.sim_clock
    clock = SimClock() if sim else WallClock()
    ctrl = Controller(cfg, policy, start_pose_mm=start, lockstep=args.lockstep, localise=args.localiser == "on",
                      profile=prof)
    if args.robot_map is None and args.storage:  # the map the robot was last given (qnav map upload)
        from firmware_py.mapdata import MapDataError, grid_from_map_file
        from firmware_py.storage import Storage, boot_map_candidates

        for path in boot_map_candidates(Storage(args.storage)):
            try:
                ok, why = ctrl.set_robot_map(grid_from_map_file(path, cfg.cell_size_mm))
            except (MapDataError, OSError, UnicodeDecodeError) as exc:
                ok, why = False, str(exc)
            if ok:
                break
            logging.getLogger("qnav.robot").warning("boot map %s rejected: %s", path, why)
    elif args.robot_map is not None:
        ok, why = ctrl.set_robot_map(args.robot_map)
        if not ok:
            raise UsageError(f"--map {args.map}: {why}")
    drive = None
    if prof is not None:
        from firmware_py.drives import open_drive

        try:
            drive = open_drive(prof)
        except ValueError as exc:
            raise UsageError(f"--profile {prof.source}: {exc}") from None
    try:
        bus = open_bus(args.can)
    except CanSpecError as exc:
        raise UsageError(str(exc)) from None
    if args.rt_priority is not None and not 1 <= args.rt_priority <= 99:
        raise UsageError(f"--rt-priority {args.rt_priority}: expected 1..99")
    if not 0 <= args.gil_switch_us <= 100_000:
        raise UsageError(f"--gil-switch-us {args.gil_switch_us}: expected 0..100000")
    node = RobotNode(bus, ctrl, clock, lockstep=args.lockstep, rt_priority=args.rt_priority, drive=drive)
    runner = None
    if goals:
        runner = GoalRunner(ctrl, goals)
        node.after_tick.append(runner)
    attached = [ext.attach(node, args) for ext in EXTENSIONS]  # the MAVLink shell attaches here
    stoppers = [stop for stop in attached if stop is not None]
    log = logging.getLogger("qnav.robot")
    if onboard is not None:
        def stats_line() -> str:
            st = ctrl.status()
            return (f"stats state={st.state.name} mode={ctrl.mode.name} armed={int(ctrl.armed)} ticks={node.ticks} "
                    f"overruns={node.overruns} late={node.wall_late_ticks} can_errors={node.can_errors} "
                    f"pose_mm={st.x_mm},{st.y_mm},{st.heading_mrad}")

        onboard.start_stats(stats_line)
    log.info("policy %s, start (%d, %d) mm %d mrad, %d goal(s), %s clock",
             f"0x{policy.policy_id:08x} {policy.kind}" if policy else "none", *start, len(goals),
             "lockstep sim" if args.lockstep else "paced sim" if sim else "wall")
    wall0 = time.monotonic()
    cpu0 = time.process_time()
    code = EXIT_OK

    def on_term(_sig: int, _frame: object) -> None:  # systemd's stop (or a plain kill): the Ctrl-C path
        raise KeyboardInterrupt

    previous_term = signal.signal(signal.SIGTERM, on_term)
    node.start()
    from firmware_py.sdnotify import ServiceNotifier

    service = ServiceNotifier.from_env()  # systemd (docs/deploy.md): READY, a watchdog pet while ticks advance
    service.start(lambda: node.ticks, lambda: f"{ctrl.state.name}, {node.ticks} ticks")
    try:
        reported = False
        while True:
            if runner is not None and not reported and runner.done.wait(0.05):
                reported = True
                if runner.result != "reached":
                    log.warning("%s", runner.result)
                    code = EXIT_FAULT
                if args.exit_when_done:
                    break
            else:
                time.sleep(0.05)
            if args.duration is not None:
                elapsed = clock.now_us() / 1e6 if sim else time.monotonic() - wall0
                if elapsed >= args.duration:
                    if runner is not None and not runner.done.is_set():
                        log.warning("duration reached with goals pending")
                        code = EXIT_TIMEOUT
                    break
    except KeyboardInterrupt:
        code = 130
    finally:
        signal.signal(signal.SIGTERM, previous_term)
        service.stop()
        for stop in stoppers:
            stop()
        node.stop()
        bus.shutdown()
        log.info("stopped: %s", ctrl.status().state.name)
    wall = time.monotonic() - wall0
    cpu = time.process_time() - cpu0
    st = ctrl.status()
    summary = {
        "result": runner.result if runner else "",
        "state": st.state.name, "fault": st.fault,
        "pose_mm": [st.x_mm, st.y_mm, st.heading_mrad],
        "sim_time_s": clock.now_us() / 1e6 if sim else None,
        "wall_s": wall, "cpu_s": cpu, "cpu_percent": 100 * cpu / wall if wall > 0 else 0.0,
        "rss_mb": _rss_mb(), "ticks": node.ticks, "sim_ticks": node.sim_ticks,
        "overruns": node.overruns, "can_errors": node.can_errors, "send_errors": node.send_errors,
        # implausible inputs refused rather than used: sim-time jumps (HIL) and encoder jumps
        "refused_clock_jumps": getattr(clock, "refused_jumps", 0), "refused_sim_ticks": node.tick_gate.refused,
        "late_sim_ticks": node.late_ticks,
        "encoder_jumps": ctrl.encoder_jumps,
        # commands the collision monitor slowed or stopped (control/collision.py)
        "collision_slow_ticks": ctrl.collision_ticks["slow"], "collision_stop_ticks": ctrl.collision_ticks["stop"],
        "stalls": ctrl.stall.count,  # drives held for getting nowhere for NAV_STALL_S (control/progress.py)
        "profile": prof.source if prof else None, "drive_backend": prof.drive.backend if prof else "qnav",
        "sensor_backend": prof.sensors.backend if prof else "qnav", **node.drive.stats(),
        "planner_searches": ctrl.background.runs, "planner_search_cpu_s": ctrl.background.cpu_ns / 1e9,
        "period_us": cfg.control_period_us, "rt_priority": args.rt_priority,
        "rt_active": node.rt_active,
        **node.latency_stats(),
        **{k: v for ext in EXTENSIONS for k, v in getattr(ext, "stats", dict)().items()},
        "transitions": [[t.t_us, t.src.name, t.dst.name, t.cause] for t in ctrl.transitions],
    }
    log.info("done: %s, %d ticks, sim %.1f s, wall %.2f s, p99 %.0f us",
             summary["result"] or summary["state"], node.ticks,
             (summary["sim_time_s"] or 0.0), wall, summary["tick_p99_us"])
    if args.stats_json:
        atomic_write(args.stats_json, json.dumps(summary, indent=1))
    return code


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    dump_stacks_on_sigusr1()
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format="qnav-robot %(levelname)s %(message)s", stream=sys.stderr)
    try:
        return run(args)
    except UsageError as exc:
        print(f"qnav-robot: error: {exc}", file=sys.stderr)
        return EXIT_USAGE


def program() -> int:
    """`qnav-robot`, the program (pyproject.toml's entry point): run as on the robot, where numpy is not
    installed (firmware_py's dependencies leave it out). Where the station's packages share the
    environment (HIL, the demo) pymavlink would load it for extras the robot never calls (mavextra's
    Quaternion: 0.18 s of CPU at every start); barred, pymavlink leaves them out as it does without
    numpy, and anything on the robot's path that needed numpy would fail here as on the robot."""
    if "numpy" not in sys.modules:
        sys.modules["numpy"] = None  # type: ignore[assignment]  # None in sys.modules: "not installed"
    return main()


if __name__ == "__main__":
    sys.exit(program())
