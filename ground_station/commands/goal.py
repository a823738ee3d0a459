"""`qnav goal X Y`: send a goal in world metres (x east, y north) in Guided mode.

Sent as SET_POSITION_TARGET_LOCAL_NED (north = Y, east = X). The robot
answers an accepted goal with POSITION_TARGET_LOCAL_NED and a refused one
with a STATUSTEXT "goal refused: ..." (exit 3); silence -> exit 4.
"""

from __future__ import annotations

import argparse
import time


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.mavlink.link import add_link_args

    p = sub.add_parser("goal", help="send a goal position (Guided mode, MAVLink)", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("x", type=float, metavar="X", help="east, metres (world frame)")
    p.add_argument("y", type=float, metavar="Y", help="north, metres (world frame)")
    add_link_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ground_station.mavlink.link import (
        EXIT_REFUSED,
        LinkError,
        mavlink,
        run_on_link,
    )

    m = mavlink()
    mask = 0xFFF8  # position only

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
