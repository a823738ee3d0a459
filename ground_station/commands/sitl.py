"""`qnav sitl`: a simulated robot that stays up for MAVProxy, QGroundControl,
MAVSDK, qnav.

Starts a CAN bus (a python-can-remote hub on 127.0.0.1 unless --can names
one, e.g. socketcan:vcan0), `qnav-sim` paced at --speed times real time and
`qnav-robot` on the sim's clock with a policy loaded, waits for the robot's
HEARTBEAT, prints the MAVLink connection strings and the CAN spec, and keeps
everything running until Ctrl-C (or SIGTERM, or --duration). Every process
it started is stopped on the way out; the run folder keeps sim.log,
robot.log, the robot's file store, can.blf, trajectory.csv, mavlink.tlog (on
UDP the robot sits behind a relay that records its MAVLink both ways,
whichever ground station connects) and run.mcap, the whole run for Foxglove,
written on the way out with a progress line each second.

    qnav sitl                                   # paper10, its shipped cell
                                                # policy, real time
    mavproxy.py --master=udpout:127.0.0.1:14555 # in another terminal
    qnav sitl --can socketcan:vcan0 --speed 2   # a kernel vcan0:
                                                # candump -L vcan0 watches

Exit status: 0 stopped by Ctrl-C/SIGTERM/--duration, 1 a process died,
2 bad arguments or a failed bring-up.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from firmware_py.mavlink.telemetry import AUTOPILOTS, DEFAULT_AUTOPILOT
    from ground_station.sitl import DEFAULT_MAP, DEFAULT_MAVLINK

    p = sub.add_parser("sitl", help="bring up sim + robot and keep them running for MAVProxy/QGroundControl",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--map", default=DEFAULT_MAP, metavar="NAME|PATH",
                   help="built-in map name or a MovingAI .map file (default %(default)s)")
    p.add_argument("--policy", metavar="FILE.qtab",
                   help="policy the robot boots with: a file, policies:NAME, or 'none' (upload one later over "
                        "MAVLink FTP); default policies:paper10_cell on paper10, else policies:sector")
    p.add_argument("--can", metavar="SPEC",
                   help="CAN bus for sim and robot: socketcan:vcan0, socketcan:can0, remote:ws://HOST:PORT/ "
                        "(default: a python-can-remote hub on 127.0.0.1, free port)")
    p.add_argument("--speed", type=float, default=1.0, metavar="X",
                   help="sim pace in times real time (default %(default)g); above 1 FS_GCS_TOUT_MS is raised "
                        "to match, as the robot measures the GCS failsafe on sim time")
    p.add_argument("--lockstep", action="store_true",
                   help="the sim waits for the robot's command every tick and runs at most --speed times real "
                        "time: a loaded machine slows the run instead of tripping the motor watchdog (default: "
                        "paced, the sim never waits, as a real robot's world does not)")
    p.add_argument("--mavlink", default=DEFAULT_MAVLINK, metavar="URL",
                   help="the robot's MAVLink connection string (default %(default)s: it listens, ground "
                        "stations send to it; udpout:127.0.0.1:14550 feeds a QGroundControl directly)")
    p.add_argument("--autopilot", choices=sorted(AUTOPILOTS), default=DEFAULT_AUTOPILOT,
                   help="autopilot type the robot's HEARTBEAT gives (default %(default)s; 'ardupilot' for MAVSDK, "
                        "which decodes int parameters and names flight modes only for ArduPilot or PX4)")
    p.add_argument("--profile", type=Path, metavar="FILE.toml",
                   help="robot profile (docs/robot-profile.md): the robot drives through its backends and the sim "
                        "plays the same boards (default: qnav's own frames)")
    p.add_argument("--out", type=Path, metavar="DIR", help="run folder (default runs/sitl-<timestamp>/)")
    p.add_argument("--seed", type=int, default=0, help="sim noise seed (default %(default)s)")
    p.add_argument("--duration", type=float, metavar="S",
                   help="stop after S wall seconds (default: run until Ctrl-C)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import signal

    from ground_station.sitl import Sitl, SitlOptions, connection_help, describe_exits

    opts = SitlOptions(map_name=args.map, policy=args.policy, can=args.can, speed=args.speed, lockstep=args.lockstep,
                       mavlink=args.mavlink, out=args.out, seed=args.seed, duration_s=args.duration,
                       autopilot=args.autopilot, profile=args.profile.resolve() if args.profile else None)

    def say(line: str) -> None:
        print(f"qnav sitl: {line}", file=sys.stderr, flush=True)

    stopped_by = ["Ctrl-C"]

    def on_term(_sig, _frame):  # a plain `kill`: the same clean stop as Ctrl-C
        stopped_by[0] = "SIGTERM"
        raise KeyboardInterrupt

    sitl = Sitl(opts, say)  # validates the options
    previous = signal.signal(signal.SIGTERM, on_term)
    verdict, child_died = "interrupted", False
    try:
        try:
            info = sitl.start()
            for line in connection_help(info):
                print(line, flush=True)
            result = sitl.wait()
            verdict, child_died = result.reason, result.child_died
        except KeyboardInterrupt:
            verdict = f"stopped ({stopped_by[0]})"
        finally:
            # a second Ctrl-C must not cut the clean-up short, nor turn the finished stop into a
            # KeyboardInterrupt exit: SIGINT stays ignored until the last line is out
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            codes = sitl.stop()
        say(f"{verdict}; every process stopped ({describe_exits(codes)})")
    finally:
        signal.signal(signal.SIGTERM, previous)
    # not the previous handler: a Ctrl-C while the interpreter shuts down (joining threads, freeing
    # modules) would end a finished, clean stop as "killed by SIGINT"; stopping is done, so it is a no-op
    signal.signal(signal.SIGINT, lambda _sig, _frame: None)
    return 1 if child_died else 0
