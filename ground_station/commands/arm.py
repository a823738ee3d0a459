"""`qnav arm` / `qnav disarm`: MAV_CMD_COMPONENT_ARM_DISARM, waiting for the ACK.

A refusal exits 3 with the robot's reason (e.g. "arm refused: sensors
stale"); no ACK after the retries exits 4.
"""

from __future__ import annotations

import argparse

COMMANDS = ("arm", "disarm")  # the subcommands this module adds (ground_station.commands.add_module_subparsers)

def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.mavlink.link import add_link_args

    for verb, text in (("arm", "arm the robot (motors enabled)"), ("disarm", "disarm the robot (motors stop)")):
        p = sub.add_parser(verb, help=f"{text} (MAVLink)", description=__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        add_link_args(p)
        p.set_defaults(func=run, arm=verb == "arm")


def run(args: argparse.Namespace) -> int:
    from ground_station.mavlink.link import mavlink, run_on_link

    verb = "arm" if args.arm else "disarm"

    def body(link) -> int:
        link.command(mavlink().MAV_CMD_COMPONENT_ARM_DISARM, 1 if args.arm else 0)
        print(f"{verb}ed" if args.arm else "disarmed")
        return 0

    return run_on_link(args, verb, body)
