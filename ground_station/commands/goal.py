"""`qnav goal X Y`: send a goal in world metres (x east, y north) in Guided mode.

Sets mode Guided first (MAV_CMD_DO_SET_MODE, as a MAVProxy user types `mode
guided` before a goal: the robot, like ArduPilot Rover, takes a position
target in Guided only and never switches to Guided for one; a refused mode
exits 3 with the robot's reason), then sends the goal as
SET_POSITION_TARGET_LOCAL_NED (north = Y, east = X). The robot answers an
accepted goal with POSITION_TARGET_LOCAL_NED and a refused one with a
STATUSTEXT "goal refused: ..." (exit 3); silence -> exit 4. X and Y must be
finite numbers within the robot's local range (200 km), else exit 2 before
connecting.

With `--plan` (for sector policies, which steer to the bearing of the
current target and need the planner's intermediate waypoints) the goal goes
instead as a mission of the planner's waypoints (on `--map`, by default the
robot's own map, read from its active policy) from the robot's position (its
LOCAL_POSITION_NED, or `--start X,Y`) to the goal's cell, and the robot is
switched to Auto to drive it. `--profile FILE.toml`: segments that keep the
profile's body clear, as `qnav mission upload --plan --profile` plans them
(default the built-in robot's). `--start` and `--profile` need `--plan`.
"""

from __future__ import annotations

import argparse

from firmware_py.vehicle import Mode
from ground_station.mavlink.link import add_link_args, finite_float, run_on_link


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.mavlink.mission_items import add_profile_arg

    p = sub.add_parser("goal", help="send a goal position (Guided mode, MAVLink)", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("x", type=finite_float, metavar="X", help="east, metres (world frame)")
    p.add_argument("y", type=finite_float, metavar="Y", help="north, metres (world frame)")
    p.add_argument("--plan", action="store_true",
                   help="send the planner's waypoints to the goal as a mission and start it (sector policies)")
    p.add_argument("--map", metavar="NAME|PATH",
                   help="--plan: the map (default: the robot's, from its active policy; another is refused)")
    p.add_argument("--start", metavar="X,Y", help="--plan: start position in metres (default: the robot's)")
    add_profile_arg(p)
    add_link_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from firmware_py.mavlink.mission import LOCAL_LIMIT_M
    from ground_station.errors import CliError
    from ground_station.mavlink.mission_items import profile_radius_arg

    if max(abs(args.x), abs(args.y)) > LOCAL_LIMIT_M:  # the robot's local-frame range (float32 on the wire)
        raise CliError(f"goal ({args.x:g}, {args.y:g}) m is out of range (|X|, |Y| <= {LOCAL_LIMIT_M:g} m)")
    if args.start and not args.plan:
        raise CliError("--start needs --plan")
    if args.plan:
        return _planned_goal(args)
    profile_radius_arg(args)  # --profile without --plan: refused

    def body(link) -> int:
        link.command(link.m.MAV_CMD_DO_SET_MODE, link.m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(Mode.GUIDED))
        link.set_goal(args.x, args.y)
        print(f"goal x={args.x:g} y={args.y:g} m accepted (mode Guided)")
        return 0

    return run_on_link(args, "goal", body)


def _planned_goal(args: argparse.Namespace) -> int:
    """Upload the planned waypoints to (X, Y) as a mission and set mode Auto."""
    from ground_station.mavlink.mission_items import (
        body_text,
        goal_cell,
        load_gridmap,
        parse_start,
        planned_goal_items,
        profile_radius_arg,
        robot_position_mm,
    )
    from ground_station.mavlink.robot_map import choose_map

    start = parse_start(args.start) if args.start else None  # bad input is refused before connecting
    radius_mm = profile_radius_arg(args)
    given = load_gridmap(args.map) if args.map is not None else None
    if given is not None:  # a bad map or goal fails before any link
        goal_cell(given, args.x, args.y)

    def body(link) -> int:
        gm = choose_map(link, given)
        goal_cell(gm, args.x, args.y)
        items = planned_goal_items(gm, args.x, args.y, start if start is not None else robot_position_mm(link),
                                   radius_mm)
        n = link.mission_upload(items)
        link.command(link.m.MAV_CMD_DO_SET_MODE, link.m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(Mode.AUTO))
        print(f"goal x={args.x:g} y={args.y:g} m: mission of {n} planned waypoints{body_text(radius_mm)} accepted, "
              "mode Auto")
        return 0

    return run_on_link(args, "goal", body)
