"""`qnav mode hold|guided|auto|manual`: MAV_CMD_DO_SET_MODE with the Rover
custom mode.

Modes are numbered as ArduPilot Rover (Manual 0, Hold 4, Auto 10, Guided
15), so stock ground stations name them. Waits for the ACK; a refusal exits
3 with the robot's reason (e.g. Auto without a mission). Mode names take any
case (`qnav mode MANUAL`, as MAVProxy's `mode MANUAL`).
"""

from __future__ import annotations

import argparse

MODES = {"hold": 4, "guided": 15, "auto": 10, "manual": 0}  # firmware_py.vehicle.Mode


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.mavlink.link import add_link_args

    p = sub.add_parser("mode", help="set the robot's mode (MAVLink)", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("mode", type=str.lower, choices=sorted(MODES), metavar="MODE",
                   help="hold | guided | auto | manual (then qnav drive); any case, HOLD as MAVProxy names it")
    add_link_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from firmware_py.vehicle import Mode
    from ground_station.mavlink.link import mavlink, run_on_link

    assert all(Mode[k.upper()] == v for k, v in MODES.items())
    m = mavlink()

    def body(link) -> int:
        link.command(m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, MODES[args.mode])
        print(f"mode {args.mode}")
        return 0

    return run_on_link(args, "mode", body)
