"""`qnav goal X Y`: send a goal in world metres (x east, y north) in Guided mode.

Sent as SET_POSITION_TARGET_LOCAL_NED (north = Y, east = X). The robot
answers an accepted goal with POSITION_TARGET_LOCAL_NED and a refused one
with a STATUSTEXT "goal refused: ..." (exit 3); silence -> exit 4.

With `--plan` (for sector policies, which steer to the bearing of the
current target and need the planner's intermediate waypoints) the goal
goes instead as a mission of the planner's waypoints (`--map`) from the
robot's position (its LOCAL_POSITION_NED, or `--start X,Y`) to the goal's
cell, and the robot is switched to Auto to drive it.
"""

from __future__ import annotations

import argparse
import time


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.mavlink.link import add_link_args, finite_float

    p = sub.add_parser("goal", help="send a goal position (Guided mode, MAVLink)", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("x", type=finite_float, metavar="X", help="east, metres (world frame)")
    p.add_argument("y", type=finite_float, metavar="Y", help="north, metres (world frame)")
    p.add_argument("--plan", action="store_true",
                   help="send the planner's waypoints to the goal as a mission and start it (sector policies)")
    p.add_argument("--map", default="paper10", metavar="NAME|PATH", help="--plan: the map (default paper10)")
    p.add_argument("--start", metavar="X,Y", help="--plan: start position in metres (default: the robot's)")
    add_link_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from firmware_py.mavlink.mission import LOCAL_LIMIT_M
    from ground_station.errors import CliError
    from ground_station.mavlink.link import (
        EXIT_REFUSED,
        LinkError,
        mavlink,
        run_on_link,
    )

    if max(abs(args.x), abs(args.y)) > LOCAL_LIMIT_M:  # the robot's local-frame range (float32 on the wire)
        raise CliError(f"goal ({args.x:g}, {args.y:g}) m is out of range (|X|, |Y| <= {LOCAL_LIMIT_M:g} m)")
    if args.start and not args.plan:
        raise CliError("--start needs --plan")
    m = mavlink()
    mask = 0xFFF8  # position only
    if args.plan:
        from ground_station.mavlink.mission_items import parse_start

        start = parse_start(args.start) if args.start else None  # bad input refused before connecting
        return run_on_link(args, "goal", lambda link: planned_goal(args, link, start))

    def refused(t: str) -> bool:
        return t.startswith("goal refused")

    def body(link) -> int:
        since = len(link.texts)
        for _ in range(3):
            link.conn.mav.set_position_target_local_ned_send(0, link.sysid, link.compid, m.MAV_FRAME_LOCAL_NED,
                                                            mask, args.y, args.x, 0, 0, 0, 0, 0, 0, 0, 0, 0)
            end = time.monotonic() + 1.5
            while time.monotonic() < end:
                reply = link.recv("POSITION_TARGET_LOCAL_NED", min(0.1, end - time.monotonic()))
                # the refusal is a whole (reassembled) STATUSTEXT, however many chunks it took
                reason = link.wait_text(since, refused, 0.0)
                if reason is not None:
                    raise LinkError(EXIT_REFUSED, reason)
                if reply is not None and abs(reply.x - args.y) < 0.01 and abs(reply.y - args.x) < 0.01:
                    print(f"goal x={args.x:g} y={args.y:g} m accepted")
                    return 0
        raise link.no_answer("goal: no echo from the robot")

    return run_on_link(args, "goal", body)


def planned_goal(args: argparse.Namespace, link, start_mm: tuple[float, float] | None) -> int:
    """Upload the planned waypoints to (X, Y) as a mission and set mode Auto."""
    from firmware_py.mavlink.frames import LOCAL_ITEM_SCALE
    from firmware_py.vehicle import Mode
    from ground_station.errors import CliError
    from ground_station.maps import MapError, load_map
    from ground_station.mavlink.link import mavlink
    from ground_station.mavlink.mission_items import planned_items, robot_position_mm

    try:
        gm = load_map(args.map)
    except (MapError, OSError) as exc:
        raise CliError(str(exc)) from None
    cell = gm.cell_size_m
    col, row = int(args.x // cell), gm.height - 1 - int(args.y // cell)
    if not gm.in_bounds(col, row) or not gm.is_free(col, row):
        raise CliError(f"goal ({args.x:g}, {args.y:g}) m is not in a free cell of map {gm.name}")
    start = start_mm if start_mm is not None else robot_position_mm(link)
    items, _ = planned_items([(col, row)], start, gm)
    m = mavlink()
    frame = m.MAV_FRAME_LOCAL_NED
    items[-1] = (frame, round(args.y * LOCAL_ITEM_SCALE), round(args.x * LOCAL_ITEM_SCALE))  # the goal itself, not its cell's centre
    n = link.mission_upload(items)
    link.command(m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(Mode.AUTO))
    print(f"goal x={args.x:g} y={args.y:g} m: mission of {n} planned waypoints accepted, mode Auto")
    return 0
