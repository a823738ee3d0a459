"""`qnav mission upload --targets A,B,C,D | FILE` and `qnav mission download`.

Upload: waypoints from map targets (their cell centres in world metres, on
`--map`, by default the robot's own map, read from the robot over MAVLink
FTP: /maps/active.map with the targets `qnav map upload` left beside it,
else the map its active policy carries; a `--map` that is not the robot's is
refused naming both) or from a QGC WPL 110 file (as written by MAVProxy,
QGroundControl or `mission download --out`), sent through the MAVLink
mission protocol; waits for MISSION_ACK and exits 3 with the robot's reason
on refusal, 4 on timeout. Target and planned waypoints travel as
MISSION_ITEM_INT in MAV_FRAME_GLOBAL_RELATIVE_ALT, latitude/longitude around
the robot's geodetic origin (its GPS_GLOBAL_ORIGIN, = ORIGIN_LAT/LON), so
MAVProxy's `wp list`, its map and QGroundControl's plan view show them where
the robot is; the robot converts them back to within 6 mm (1e-7 deg steps).
`--frame local` sends them in MAV_FRAME_LOCAL_NED (x north, y east, exact to
0.1 mm; stock maps cannot place those). A FILE's items go in the frames it
gives (`--frame global` converts its local ones). With `--plan` the ground
station's planner (`ground_station.maps.planner`, what the sector policy is
trained to follow) fills in the waypoints from the robot's position (its
LOCAL_POSITION_NED, or `--start X,Y` in metres) through the targets on the
map (`--profile FILE.toml`: segments that keep the profile's body clear, as
`qnav train --profile` trained a sector policy with; default the built-in
robot's); the planned legs are printed. `--plan --follow` then stays on the
link while the robot drives (start it with `qnav arm` and `qnav mode auto`):
when it reports that it stopped progressing, the cells its range readings
(OBSTACLE_DISTANCE, each at the angle of the `--profile`'s sensor that read
it) found blocked are marked on the ground station's copy of the map and the
rest of the mission is planned again, round the same body (`--profile`'s),
and uploaded (`ground_station.nav.replan`); exits 0 when every target is
reached, 3 when it gives up (no new blocked cell, no path left), 4 after
`--follow-timeout`.

Without `--plan`, targets sent to a robot whose active policy is a sector
policy that steers to the planner's waypoints (trained with
`--sector-guidance path`, the shipped recipe's) are planned all the same,
with the margins and body radius that policy was trained with (read from its
file on the robot, as the map is): the table only ever learnt to reach the
next of those waypoints, a few cells off with the map leaving the straight
line clear; sent the targets alone it steers straight at targets metres away
with walls between, where its twin's `direct` column says it fails.
`--no-plan` sends the targets alone.

Download: prints the robot's mission in the frames it was uploaded in (world
metres, x east / y north, beside the latitude/longitude of global items) and
with `--out FILE` writes it as QGC WPL 110.
"""

from __future__ import annotations

import argparse
import math

from ground_station.commands import add_actions
from ground_station.errors import CliError


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.mavlink.link import add_link_args
    from ground_station.mavlink.mission_items import add_profile_arg

    verbs = add_actions(sub, "mission", "upload or download the robot's mission (MAVLink)", __doc__, "verb", "VERB")
    up = verbs.add_parser("upload", help="upload waypoints (map targets or a WPL file)")
    up.add_argument("file", nargs="?", metavar="FILE", help="QGC WPL 110 waypoint file")
    up.add_argument("--targets", metavar="A,B,...", help="map target names, in visiting order")
    up.add_argument("--map", metavar="NAME|PATH",
                    help="map of the targets (default: the robot's own /maps/active.map, else its policy's map)")
    up.add_argument("--cell-size", type=float, default=None, metavar="M",
                    help="cell size in metres (default: the map's, 0.5)")
    up.add_argument("--plan", action="store_true",
                    help="send the planner's waypoints through the targets (what a sector policy needs)")
    up.add_argument("--no-plan", action="store_true",
                    help="send the targets alone, also to a robot whose sector policy steers to the planner's "
                         "waypoints (planned for it by default)")
    up.add_argument("--start", metavar="X,Y", help="--plan: start position in metres (default: the robot's)")
    add_profile_arg(up)
    up.add_argument("--follow", action="store_true",
                    help="--plan: watch the mission and re-plan around cells the robot finds blocked")
    up.add_argument("--follow-timeout", type=float, default=600.0, metavar="S",
                    help="--follow: give up after this many seconds (default 600)")
    up.add_argument("--frame", choices=("global", "local"), default=None,
                    help="frame of the waypoints sent: global (lat/lon around the robot's origin, what maps "
                         "show; default for --targets) or local (LOCAL_NED metres; default: a FILE's own frames)")
    down = verbs.add_parser("download", help="print the robot's mission")
    down.add_argument("--out", metavar="FILE", help="also write it as a QGC WPL 110 file")
    for v in (up, down):
        add_link_args(v)
        v.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from firmware_py.mavlink.frames import LOCAL_ITEM_SCALE
    from ground_station.mavlink.link import run_on_link
    from ground_station.mavlink.mission_items import (
        file_items,
        load_gridmap,
        parse_start,
        profile_radius_arg,
        target_items,
        write_wpl,
    )

    if args.verb == "upload":
        if bool(args.targets) == bool(args.file):
            raise CliError("give either --targets A,B,... or a waypoint FILE")
        if args.plan and not args.targets:
            raise CliError("--plan needs --targets A,B,...")
        if args.plan and args.no_plan:
            raise CliError("give --plan or --no-plan, not both")
        if args.start and not args.plan:
            raise CliError("--start needs --plan")
        if args.follow and not args.plan:
            raise CliError("--follow needs --plan")
        radius_mm = profile_radius_arg(args)  # a bad profile fails before any link
        if not (math.isfinite(args.follow_timeout) and args.follow_timeout > 0):
            raise CliError(f"--follow-timeout must be a positive number of seconds, got {args.follow_timeout:g}")
        items = file_items(args.file) if args.file else []
        start = parse_start(args.start) if args.start else None
        given = load_gridmap(args.map, args.cell_size) if args.map is not None else None
        if args.targets and given is not None:  # a bad map or target fails before any link
            target_items(args.targets, given)

        def upload(link) -> int:
            nonlocal items
            target_seq: list[int] = []
            if (args.frame or ("global" if args.targets else "local")) == "global":
                from ground_station.mavlink.link import LinkError

                try:
                    link.use_global_frame()  # LOCAL_NED items (targets, plans, re-plans) go around the origin
                except LinkError as exc:
                    raise LinkError(exc.code, f"{exc}; --frame local sends the waypoints in metres") from None
            gm = None
            if args.targets:
                from ground_station.mavlink.robot_map import choose_map

                gm = choose_map(link, given)
                items = target_items(args.targets, gm)
            if args.plan:
                items, target_seq = plan_mission(args, link, start, gm, radius_mm)
            elif args.targets and not args.no_plan:
                follows = waypoint_policy(link)
                if follows is not None:  # its table steers to the planner's waypoints: send it those
                    policy_id, plan_kw = follows
                    print(f"the robot's policy 0x{policy_id:08x} is a sector policy that steers to the planner's "
                          "waypoints: planning them (--no-plan sends the targets alone)")
                    items, target_seq = plan_mission(args, link, None, gm, plan_kw=plan_kw)
            n = link.mission_upload(items)
            print(f"mission of {n} waypoints accepted")
            if not args.follow:
                return 0
            from firmware_py import robot_spec
            from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
            from firmware_py.profile import load_profile
            from ground_station.mavlink.mission_items import target_cells
            from ground_station.nav.replan import MissionFollower, follow_mission

            assert gm is not None  # --follow needs --plan, which needs --targets
            # the profile's sensors place each range reading (it loaded above, before any link)
            layout = load_profile(args.profile).layout() if args.profile else DEFAULT_LAYOUT
            follower = MissionFollower(gm, target_cells(args.targets, gm), target_seq,
                                       radius_mm=robot_spec.ROBOT_RADIUS_MM if radius_mm is None else radius_mm,
                                       layout=layout)
            print(f"following the mission (up to {args.follow_timeout:g} s) ...", flush=True)
            done = follow_mission(link, follower, args.follow_timeout, lambda line: print(line, flush=True))
            print(done.text)
            return 0 if done.ok else 4 if done.text.startswith("timeout") else 3

        return run_on_link(args, "mission upload", upload)

    def download(link) -> int:
        from firmware_py.mavlink.frames import global_to_world

        items = link.mission_download()
        m = link.m
        origin = link.origin() if any(it.frame != m.MAV_FRAME_LOCAL_NED for it in items) else None
        print(f"{len(items)} items")
        for it in items:
            if it.frame == m.MAV_FRAME_LOCAL_NED:
                print(f"{it.seq:3d} local  x={it.y / LOCAL_ITEM_SCALE:.3f} m east  "
                      f"y={it.x / LOCAL_ITEM_SCALE:.3f} m north")
            else:
                assert origin is not None
                x_mm, y_mm = global_to_world(it.x, it.y, origin[0], origin[1])
                print(f"{it.seq:3d} global lat={it.x / 1e7:.7f} lon={it.y / 1e7:.7f} (frame {it.frame})  "
                      f"x={x_mm / 1000:.3f} m east  y={y_mm / 1000:.3f} m north")
        if args.out:
            write_wpl(args.out, items)
        return 0

    return run_on_link(args, "mission download", download)


def waypoint_policy(link) -> tuple[int, dict] | None:
    """(policy id, `plan_waypoints` keywords) when the robot's active policy (its file on the robot) is
    a sector policy trained to steer to the planner's waypoints: the margin, longest segment and body
    radius it was trained with. None for any other policy, none, or one that cannot be read."""
    from ground_station.maps.planner import guidance_from_metadata
    from ground_station.mavlink.robot_map import robot_policy

    try:
        pol = robot_policy(link)
    except CliError:  # not in its storage, or no FTP server: the targets as given
        return None
    meta = pol.metadata if pol is not None and isinstance(pol.metadata, dict) else None
    if pol is None or pol.kind != "sector" or meta is None:
        return None
    if (meta.get("config") or {}).get("sector_guidance", "path") != "path":
        return None  # trained on the goal's bearing alone (direct)
    kw = guidance_from_metadata(meta)
    radius = (meta.get("robot_needs") or {}).get("robot_radius_mm_max")
    if radius:
        kw["radius_mm"] = float(radius)
    return pol.policy_id, kw


def plan_mission(args: argparse.Namespace, link, start_mm: tuple[float, float] | None,
                 gm, radius_mm: float | None = None,
                 plan_kw: dict | None = None) -> tuple[list[tuple[int, int, int]], list[int]]:
    from ground_station.mavlink.mission_items import (
        body_text,
        planned_items,
        robot_position_mm,
        target_cells,
    )

    start = start_mm if start_mm is not None else robot_position_mm(link)
    kw = dict(plan_kw or {})
    if radius_mm is not None:
        kw["radius_mm"] = radius_mm
    items, target_seq = planned_items(target_cells(args.targets, gm), start, gm, kw or None)
    print(f"planned {len(items)} waypoints{body_text(kw.get('radius_mm'))} from ({start[0] / 1000:.2f}, {start[1] / 1000:.2f}) m; "
          f"targets at items {', '.join(str(i) for i in target_seq)}")
    return items, target_seq
