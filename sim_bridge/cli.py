"""`qnav-sim`: run the pymunk plant on a CAN bus.

The plant plays the robot's motor driver, range sensors, encoders and bumper
and owns the clock (docs/can-protocol.md). Maps load through
`ground_station.maps` (built-in names or MovingAI files): the sim is a
test-PC tool, so it shares the ground station's map reader instead of
keeping a second one.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from firmware_py.helpformat import DefaultsHelpFormatter
from firmware_py.stackdump import dump_stacks_on_sigusr1
from sim_bridge.profiles import PROFILES, PlantProfile

EPILOG = """examples:
  qnav-sim --map paper10 --can virtual:qnav --lockstep --duration 30 --png run.png
  qnav-sim --map maps/room.map --can remote:ws://127.0.0.1:54701/ --realtime --log run.blf
  qnav-sim --map paper10 --can remote:ws://127.0.0.1:54701/ --speed 5 --start 1.25,1.25,90
"""


class CliError(Exception):
    pass


def _per_profile(value: Callable[[PlantProfile], float]) -> str:
    """"ideal: 10; realistic: 10": a field's value in every named profile, for the help."""
    return "; ".join(f"{name}: {value(prof):g}" for name, prof in PROFILES.items())


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="qnav-sim", description=__doc__, epilog=EPILOG,
                                formatter_class=DefaultsHelpFormatter)
    p.add_argument("--map", required=True, metavar="NAME|PATH",
                   help="built-in map name (e.g. paper10) or a MovingAI .map file")
    p.add_argument("--can", default=None, metavar="SPEC",
                   help="virtual:NAME, remote:ws://127.0.0.1:PORT/, socketcan:CHANNEL, slcan:DEVICE; "
                        "omitted: python-can's own configuration")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", action="store_true",
                      help="wait for the controller's command every tick (default; deterministic)")
    mode.add_argument("--realtime", action="store_true", help="paced at real time")
    mode.add_argument("--speed", type=float, metavar="X", help="paced at X times real time")
    p.add_argument("--max-speed", type=float, metavar="X",
                   help="lockstep, but never faster than X times real time (a real-time link such as a "
                        "radio sees at most X times its telemetry rate; a loaded machine only slows the run)")
    p.add_argument("--start", metavar="X,Y,HEADING",
                   help="start pose: metres east, metres north, heading in degrees CCW from east "
                        "(default: free cell nearest the map centre, heading east)")
    p.add_argument("--seed", type=int, default=0, help="seed of sensor noise, dropout and slip")
    p.add_argument("--duration", type=float, default=60.0, metavar="S", help="sim seconds to run")
    p.add_argument("--cell-size", type=float, default=0.5, metavar="M", help="map cell size (m)")
    p.add_argument("--plant", default=None, metavar="NAME",
                   help=f"named wheel/sensor error (sim_bridge/profiles.py: {', '.join(PROFILES)}); the options "
                        "below override its fields (default ideal)")
    p.add_argument("--profile", default=None, metavar="FILE.toml|NAME",
                   help="the robot profile whose boards the sim plays (docs/robot-profile.md: its drive backend, "
                        f"qnav, odrive or dronecan); a plant profile name ({', '.join(PROFILES)}) is taken as --plant")
    p.add_argument("--flip-wheel", choices=("left", "right"), default=None,
                   help="that wheel's motor mounted the other way round (for qnav-robot --check)")
    p.add_argument("--drive-fault", action="append", default=[], metavar="T:WHAT:SIDE",
                   help="at sim second T, the ODrive axis (or DroneCAN ESC) on SIDE (left/right) gets an axis "
                        "error (WHAT = error:0x40, any code; an ESC reports health ERROR) or falls silent "
                        "(WHAT = silent); repeatable")
    p.add_argument("--noise-mm", type=float, default=None,
                   help=f"range noise std dev (mm; {_per_profile(lambda f: f.range_noise_mm)})")
    p.add_argument("--dropout", type=float, default=None,
                   help=f"probability that a range reading is INVALID ({_per_profile(lambda f: f.range_dropout)})")
    p.add_argument("--fan-rays", type=int, default=3, help="rays per range sensor")
    p.add_argument("--slip", type=float, default=None,
                   help="encoder slip: std dev of each wheel's measured travel per physics step, as a "
                        f"fraction ({_per_profile(lambda f: f.slip_std)})")
    p.add_argument("--enc-scale-left", type=float, default=None, metavar="F",
                   help=f"left encoder's measured / true travel ({_per_profile(lambda f: f.encoder_scale[0])})")
    p.add_argument("--enc-scale-right", type=float, default=None, metavar="F",
                   help=f"right encoder's measured / true travel ({_per_profile(lambda f: f.encoder_scale[1])})")
    p.add_argument("--watchdog-ms", type=int, default=200, help="motor watchdog, sim ms")
    p.add_argument("--tick-timeout", type=float, default=1.0, metavar="S",
                   help="lockstep: wall seconds to wait for a tick's command before stepping anyway")
    p.add_argument("--start-timeout", type=float, default=30.0, metavar="S",
                   help="lockstep: wall seconds to wait for the controller's first answer")
    p.add_argument("--log", metavar="FILE", help="CAN log (.blf, .asc, ...), sim-time stamps")
    p.add_argument("--trajectory", metavar="FILE", help="ground-truth trajectory CSV")
    p.add_argument("--png", metavar="FILE", help="plot of map, trajectory, goals and last rays")
    p.add_argument("--scenario", metavar="FILE",
                   help="JSON with unmapped obstacles: \"discs\" [[x, y, r], ...] and \"movers\" "
                        "[[x, y, vx, vy, r], ...] in mm, mm/s (sim_bridge/obstacles.py; qnav demo writes it)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    return p


def parse_start(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        x, y, heading_deg = (float(v) for v in parts)
    except ValueError:
        raise CliError(f"--start {text!r}: expected X,Y,HEADING (metres, metres, degrees)") from None
    if not all(math.isfinite(v) for v in (x, y, heading_deg)):
        raise CliError(f"--start {text!r}: values must be finite")
    return x, y, math.radians(heading_deg)


def _make_output_folders(args: argparse.Namespace) -> None:
    """Create the folders of --log/--trajectory/--png before the run (a missing
    `run/` must not fail the run, nor lose its outputs at the end)."""
    for flag, value in (("--log", args.log), ("--trajectory", args.trajectory), ("--png", args.png)):
        if not value:
            continue
        folder = Path(value).parent
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CliError(f"{flag} {value}: cannot create folder {folder}: {exc.strerror or exc}") from None


def load_obstacles(plant, path: str):  # type: ignore[no-untyped-def]
    """The ObstacleLayer of a scenario JSON file; ValueError with one line if it is unusable."""
    import json

    from sim_bridge.obstacles import ObstacleLayer

    try:
        d = json.loads(Path(path).read_text())
        return ObstacleLayer(plant.world, d.get("discs", []), d.get("movers", []))
    except (OSError, ValueError, TypeError, AttributeError) as exc:
        raise ValueError(f"--scenario {path}: {exc}") from None


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from firmware_py import robot_spec
    from firmware_py.canbus import CanSpecError, open_bus
    from ground_station.maps import MapError, load_map
    from sim_bridge.motors import MotorParams
    from sim_bridge.outputs import CanLog, write_png, write_trajectory
    from sim_bridge.plant import LockstepError, Plant, SimConfig, run_lockstep, run_paced
    from sim_bridge.profiles import profile
    from sim_bridge.sensors import RangeParams
    from sim_bridge.world import Pose

    if not args.duration > 0:
        raise CliError(f"--duration must be positive, got {args.duration:g}")
    if args.speed is not None and not args.speed > 0:
        raise CliError(f"--speed must be positive, got {args.speed:g}")
    speed = 1.0 if args.realtime else args.speed
    if args.max_speed is not None and (speed is not None or not args.max_speed > 0):
        raise CliError(f"--max-speed {args.max_speed:g}: a positive factor, with --lockstep only")
    _make_output_folders(args)
    try:
        gm = load_map(args.map, cell_size_m=args.cell_size)
    except (MapError, OSError, ValueError) as exc:
        raise CliError(f"--map {args.map}: {exc}") from None
    robot, plant_name = None, args.plant or "ideal"
    if args.profile and not (args.profile.endswith(".toml") or Path(args.profile).is_file()):
        plant_name = args.profile  # a plant profile's name (the option's meaning before robot profiles)
    elif args.profile:
        from firmware_py.profile import ProfileError, load_profile
        try:
            robot = load_profile(args.profile)
        except ProfileError as exc:
            raise CliError(f"--profile {exc}") from None
    faults = []
    for text in args.drive_fault:
        parts = text.split(":")
        try:
            t, what, side = float(parts[0]), ":".join(parts[1:-1]), parts[-1]
            ok = side in ("left", "right") and (what == "silent" or (what.startswith("error:")
                                                                    and int(what[6:], 0) > 0)) and t >= 0
        except (ValueError, IndexError):
            ok = False
        if not ok:
            raise CliError(f"--drive-fault {text!r}: expected T:error:CODE:SIDE or T:silent:SIDE, "
                           "e.g. 5:error:0x40:left")
        faults.append((t, what, side))
    if faults and (robot is None or robot.drive.backend not in ("odrive", "dronecan")):
        raise CliError("--drive-fault needs --profile FILE with an odrive or dronecan drive")
    try:
        prof = profile(plant_name)
        scale = (prof.encoder_scale[0] if args.enc_scale_left is None else args.enc_scale_left,
                 prof.encoder_scale[1] if args.enc_scale_right is None else args.enc_scale_right)
        prof = replace(prof, encoder_scale=scale,
                       slip_std=prof.slip_std if args.slip is None else args.slip,
                       range_noise_mm=prof.range_noise_mm if args.noise_mm is None else args.noise_mm,
                       range_dropout=prof.range_dropout if args.dropout is None else args.dropout)
        config = SimConfig(seed=args.seed, cell_size_m=gm.cell_size_m,
                           ranges=RangeParams(args.fan_rays, prof.range_noise_mm, prof.range_dropout),
                           motors=MotorParams(watchdog_ms=args.watchdog_ms),
                           encoder_slip_std=prof.slip_std, encoder_scale=prof.encoder_scale,
                           robot=robot, flip_wheel=args.flip_wheel or "", drive_faults=tuple(faults))
        start = Pose(*parse_start(args.start)) if args.start else None
        plant = Plant(gm.occ, config, start)
        if args.scenario:
            plant.obstacles = load_obstacles(plant, args.scenario)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    try:
        bus = open_bus(args.can)
    except CanSpecError as exc:
        raise CliError(str(exc)) from None
    log = None
    try:
        if args.log:
            log = CanLog(args.log)
        ticks = math.ceil(args.duration * 1e6 / robot_spec.CONTROL_PERIOD_US)
        mode = (f"paced x{speed:g}" if speed is not None else "lockstep" if args.max_speed is None
                else f"lockstep, at most x{args.max_speed:g}")
        print(f"qnav-sim: {gm.name} ({gm.width}x{gm.height}, {gm.cell_size_m:g} m cells), "
              f"{mode}, bus {args.can or 'python-can default'}", file=sys.stderr)
        interrupted = False
        # Ctrl-C / the demo's SIGINT lands between physics steps (Plant.interrupt), never inside pymunk
        previous_sigint = signal.signal(signal.SIGINT, lambda _sig, _frame: plant.interrupt())
        with tqdm(total=ticks, unit="tick", disable=True if args.quiet else None) as bar:
            try:
                if speed is None:
                    stats = run_lockstep(plant, bus, args.duration, logger=log, progress=bar,
                                         tick_timeout_s=args.tick_timeout,
                                         start_timeout_s=args.start_timeout, max_speed=args.max_speed,
                                         on_wait=lambda line: print(f"qnav-sim: {line}", file=sys.stderr,
                                                                    flush=True))
                else:
                    stats = run_paced(plant, bus, args.duration, speed, logger=log, progress=bar)
            except KeyboardInterrupt:
                interrupted, stats = True, plant.stats
            finally:
                signal.signal(signal.SIGINT, previous_sigint)
    except (LockstepError, ValueError) as exc:
        raise CliError(str(exc)) from None
    finally:
        bus.shutdown()
        if log is not None:
            log.close(keep=True)
    if args.trajectory:
        write_trajectory(plant, args.trajectory)
    if args.png:
        goals = {name: plant.world.cell_center(c, r) for name, (c, r) in gm.targets.items()}
        # the whole run: the sim ticks on before and after a mission (`qnav demo`'s summary times the mission)
        write_png(plant, args.png, goals, title=f"{gm.name}: whole run, {stats.sim_s:.1f} s of sim time")
    pose = plant.world.pose
    wall = stats.wall_s or 1e-9
    print(f"ticks {stats.ticks} (missed {stats.missed_ticks}, stale commands "
          f"{stats.stale_commands}, bad frames {stats.bad_frames}, repeated answers {stats.repeated_answers}); "
          f"sim {stats.sim_s:.2f} s, "
          f"wall {wall:.2f} s, real-time factor {stats.sim_s / wall:.2f}"
          f"{'' if speed is None else f' (target {speed:g})'}, {stats.ticks_per_s:.0f} ticks/s; "
          f"{f'schedule slipped {stats.slipped_s:.2f} s (stalls); ' if stats.slipped_s else ''}"
          f"final pose x={pose.x:.3f} y={pose.y:.3f} heading={math.degrees(pose.heading) % 360:.1f} deg")
    return 130 if interrupted else 0


def main(argv: list[str] | None = None) -> int:
    from ground_station.extras import require_station

    require_station("qnav-sim")  # pymunk, numpy, the maps: one line, not a traceback
    args = build_parser().parse_args(argv)
    dump_stacks_on_sigusr1()
    try:
        return run(args)
    except CliError as exc:
        print(f"qnav-sim: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
