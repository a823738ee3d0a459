"""`qnav monitor`: live telemetry dashboard, plain status lines, or a replay.

    qnav monitor [--mavlink URL] [--tlog FILE] [--signing-key FILE]
        [--map NAME|PATH]
    qnav monitor --plain [--duration S]          one status line per second
    qnav monitor --replay FILE.tlog [--speed X]  a recording through the
                                                 same view
    qnav monitor --foxglove [--port P]           also a Foxglove WebSocket
                                                 bridge on 127.0.0.1:P
        [--foxglove-origin URL ...] [--foxglove-token T] [--foxglove-goals]

With --foxglove the same telemetry is published live for Foxglove (open
ws://127.0.0.1:P in Foxglove desktop or its web app): the robot's pose on
its map, range sectors, the mission, the log, every MAVLink message
(ground_station/logs/topics.py). Live links only. Clients offering either
subprotocol, foxglove.sdk.v1 (Foxglove) or foxglove.websocket.v1
(Lichtblick, older Foxglove Studio), are served.

The map (dashboard and /map) is the robot's own, read over MAVLink FTP as
`qnav mission upload` reads it (its /maps/active.map, else its policy's map)
once it is heard, and read again when its CRC changes (checked every 5 s);
/map is re-sent to every new subscriber. --map overrides it.

Who may connect: a client without an Origin header (not a web page), or a
browser page from an allowed origin (default https://app.foxglove.dev;
--foxglove-origin replaces the list, repeatable); any other page is refused
(HTTP 403), since any page in the operator's browser can reach 127.0.0.1.
With --foxglove-token T a client must also give T: ws://127.0.0.1:P/?token=T
or the header "Authorization: Bearer T" (else HTTP 401).

Read-only by default. With --foxglove-goals a goal published on /goal (JSON
{"x": E, "y": N} metres) is checked as `qnav goal` checks it and sent as
SET_POSITION_TARGET_LOCAL_NED only while the robot's HEARTBEAT says Guided
(the operator sets Guided: `qnav mode guided`); otherwise it is dropped,
with a line on stderr and on /log. The robot refuses a position target
outside Guided itself too.

Stamps are the robot's clock (its time_boot_ms: sim time in HIL) once it has
sent one. The view follows one system id (the first robot heard, or
--target-system); frames from other systems, or from a second process using
the same id (its clock runs behind), are ignored and counted on exit. Live
--plain exits 4 when no robot was heard within --timeout.
"""

from __future__ import annotations

import argparse
import os
import sys

from ground_station.errors import CliError


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("monitor", help="telemetry dashboard (live, --plain, or --replay a .tlog)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    from ground_station.mavlink.link import add_link_args

    add_link_args(p, url_default=None,
                  timeout_help="live --plain: exit 4 if no robot is heard within S seconds (> 0, default 10)")
    p.add_argument("--map", metavar="NAME|PATH",
                   help="map drawn under the robot: built-in name, generator spec or .map path; 'none' for a "
                        "blank field (default: the robot's own map, read over MAVLink FTP; paper10 in a --replay)")
    p.add_argument("--cell-size", type=float, default=0.5, metavar="M", help="map cell size in metres (default 0.5)")
    p.add_argument("--plain", action="store_true", help="no dashboard: print one status line per second")
    p.add_argument("--duration", type=float, metavar="S",
                   help="live --plain: stop after S wall-clock seconds; line stamps are the robot's clock (sim "
                        "time in HIL: at `qnav sitl --speed 4` it runs 4x wall time)")
    p.add_argument("--until-done", action="store_true",
                   help="live --plain: stop once the robot says 'mission complete' (exit 0), enters FAULT or holds "
                        "after a stall, its bumper or a GCS failsafe (exit 3); --duration still bounds the wait: "
                        "exit 4 if it ends first")
    p.add_argument("--replay", metavar="FILE.tlog", help="replay a recording instead of a live link")
    p.add_argument("--speed", type=float, default=1.0, metavar="X",
                   help="replay speed factor (default 1; 0 = as fast as possible)")
    p.add_argument("--foxglove", action="store_true",
                   help="also publish the telemetry on a Foxglove WebSocket server on 127.0.0.1 (live only)")
    p.add_argument("--port", type=int, default=8765, metavar="P",
                   help="--foxglove: the WebSocket port (default 8765, Foxglove's; 0 = any free port)")
    p.add_argument("--foxglove-origin", action="append", metavar="URL",
                   help="--foxglove: a browser origin allowed to connect (repeatable; replaces the default "
                        "https://app.foxglove.dev; clients sending no Origin are always allowed)")
    p.add_argument("--foxglove-token", metavar="TOKEN",
                   help="--foxglove: clients must give TOKEN (ws://127.0.0.1:P/?token=TOKEN or "
                        "'Authorization: Bearer TOKEN')")
    p.add_argument("--foxglove-goals", action="store_true",
                   help="--foxglove: let clients publish /goal (sent only while the robot is in Guided); "
                        "default read-only")
    p.set_defaults(func=run)


def _foxglove_origins(given: list[str]) -> list[str]:
    """--foxglove-origin values: scheme://host[:port] each ('none': no browser origin at all)."""
    from urllib.parse import urlsplit

    out = []
    for origin in given:
        if origin.strip().lower() == "none":
            continue
        parts = urlsplit(origin.strip())
        if parts.scheme not in ("http", "https", "file", "app") or (parts.scheme in ("http", "https") and not parts.netloc) \
                or parts.path not in ("", "/") or parts.query or parts.fragment:
            raise CliError(f"--foxglove-origin must be an origin such as https://app.foxglove.dev, got {origin!r}")
        out.append(origin)
    return out


def _load_map(spec: str, cell_size: float):
    if spec.lower() == "none":
        return None
    from ground_station.maps import MapError, load_map

    try:
        return load_map(spec, cell_size_m=cell_size)
    except (MapError, OSError) as exc:
        raise CliError(f"--map {spec}: {exc}") from exc


def _faulted(view) -> bool:
    from firmware_py.vehicle import CtrlState
    return view.ctrl_state == CtrlState.FAULT


def _stopped(view) -> str | None:
    """The robot's words when it holds for good mid-mission (statustext.holds_for_good): waiting out
    --duration tells nothing more."""
    from ground_station.mavlink.statustext import holds_for_good
    return next((line.text for line in view.log if holds_for_good(line.text)), None)


def _done(view) -> bool:
    """The robot said its mission is complete (its transition text), is in FAULT, or holds for good."""
    return _faulted(view) or any("mission complete" in line.text for line in view.log) or _stopped(view) is not None


def open_source(args):
    """The message source the flags ask for (ReplaySource or LiveSource)."""
    from ground_station.mavlink.link import _url_arg, default_url
    from ground_station.monitor.sources import ReplaySource, open_live

    if args.replay:
        if args.mavlink or args.tlog or args.signing_key:
            raise CliError("--replay reads a recording; it cannot be combined with --mavlink/--tlog/--signing-key")
        if args.duration is not None:
            raise CliError("--duration is for a live link; a replay ends with its recording")
        if args.speed < 0:
            raise CliError(f"--speed must be >= 0, got {args.speed}")
        if not os.path.isfile(args.replay):
            raise CliError(f"no such tlog: {args.replay}")
        return ReplaySource(args.replay, speed=args.speed), f"replay {os.path.basename(args.replay)} x{args.speed:g}"
    if args.tlog and args.no_tlog:
        raise CliError("--tlog and --no-tlog contradict each other")
    try:
        url = args.mavlink or _url_arg(default_url())
    except argparse.ArgumentTypeError as exc:
        raise CliError(f"--mavlink: {exc}") from None
    tlog = False if args.no_tlog else args.tlog
    try:
        source = open_live(url, tlog=tlog, signing_key=args.signing_key, target_system=args.target_system,
                           source=(args.source_system, args.source_component))
    except ValueError as exc:  # bad signing key file
        raise CliError(str(exc)) from exc
    except OSError as exc:
        raise CliError(f"cannot open {url}: {exc}") from exc
    if source.link.tlog_path is not None:
        print(f"recording to {source.link.tlog_path}", file=sys.stderr)
    return source, url


def run(args: argparse.Namespace) -> int:
    from ground_station.monitor.model import VehicleView

    if args.until_done and (not args.plain or args.replay):
        raise CliError("--until-done is for a live --plain monitor")
    if args.duration is not None and args.duration <= 0:
        raise CliError(f"--duration must be > 0, got {args.duration}")
    if args.cell_size <= 0:
        raise CliError(f"--cell-size must be > 0, got {args.cell_size}")
    if args.foxglove and args.replay:
        raise CliError("--foxglove bridges a live link; for a recording use qnav log mcap FILE.tlog")
    if not 0 <= args.port <= 65535:
        raise CliError(f"--port must be 0-65535, got {args.port}")
    origins = _foxglove_origins(args.foxglove_origin) if args.foxglove_origin else None
    if not args.foxglove and (args.foxglove_origin or args.foxglove_token is not None or args.foxglove_goals):
        raise CliError("--foxglove-origin, --foxglove-token and --foxglove-goals need --foxglove")
    if args.foxglove_token is not None and not args.foxglove_token.strip():
        raise CliError("--foxglove-token must not be empty")
    wants_map = not args.plain or args.foxglove
    map_spec = args.map if args.map is not None else ("paper10" if args.replay else None)
    grid_map = _load_map(map_spec, args.cell_size) if wants_map and map_spec is not None else None
    source, label = open_source(args)
    said: list = []  # where the robot-map lines go besides stderr (the bridge's /log)

    def say(line: str) -> None:
        print(f"qnav monitor: {line}", file=sys.stderr, flush=True)
        for also in said:
            also(line)

    if wants_map and map_spec is None:  # the robot's own map
        from ground_station.monitor.robot_map_source import RobotMapSource

        source = RobotMapSource(source, say, target_system=args.target_system)
    if args.foxglove:
        from ground_station.logs.live import DEFAULT_ORIGINS, BridgedSource, FoxgloveBridge

        try:
            bridge = FoxgloveBridge(args.port, grid_map, goals=args.foxglove_goals,
                                    origins=origins if origins is not None else DEFAULT_ORIGINS,
                                    token=args.foxglove_token)
        except Exception as exc:  # noqa: BLE001 - a port in use: one line, the link closed
            source.close()
            raise CliError(f"--foxglove: cannot serve on 127.0.0.1:{args.port}: {exc}") from None
        allowed = ", ".join(sorted(bridge.gate.origins)) or "none"
        print(f"qnav monitor: Foxglove bridge on ws://127.0.0.1:{bridge.port} "
              f"({'goals on /goal in Guided' if args.foxglove_goals else 'read-only'}; browser origins: {allowed}"
              f"{'; token required' if args.foxglove_token is not None else ''})", file=sys.stderr, flush=True)
        source = BridgedSource(source, bridge)
        said.append(bridge.say)
    view = VehicleView(sysid=args.target_system)
    try:
        if args.plain:
            from ground_station.monitor.sources import run_plain

            live = not args.replay
            from ground_station.mavlink.link import where_url_came_from

            run_plain(source, view, sys.stdout, duration=args.duration,
                      where=f" on {label}" if live else "", where_note=where_url_came_from(label) if live else "",
                      no_robot_s=args.timeout if live else None,
                      on_wait=(lambda line: print(f"qnav monitor: {line}", file=sys.stderr, flush=True))
                      if live else None, until=_done if args.until_done else None)
            if view.t is None:
                who = f"robot {args.target_system}" if args.target_system else "a robot"
                where = f"on {label}" if live else f"in {args.replay}"
                waited = f" within {args.timeout:g} s" if live and args.duration is None else ""
                print(f"qnav monitor: no HEARTBEAT from {who} {where}{waited}", file=sys.stderr)
                return 4
            if args.until_done:
                if _faulted(view):
                    print("qnav monitor: the robot entered FAULT", file=sys.stderr)
                    return 3
                stopped = _stopped(view)
                if stopped and not any("mission complete" in line.text for line in view.log):
                    print(f"qnav monitor: the robot stopped: {stopped}", file=sys.stderr)
                    return 3
                if not _done(view):
                    within = f"within {args.duration:g} s" if args.duration is not None else "before the link ended"
                    print(f"qnav monitor: the mission did not complete {within}", file=sys.stderr)
                    return 4
        else:
            from ground_station.monitor.app import MonitorApp

            MonitorApp(source, grid_map=grid_map, view=view, subtitle=label).run()
        warn_ignored(view)
        return 0
    finally:
        source.close()


def warn_ignored(view) -> None:
    """Say what the view ignored: other systems, a second process with our system id."""
    if view.foreign:
        counts = ", ".join(f"system {s}: {n}" for s, n in sorted(view.foreign.items()))
        print(f"qnav monitor: warning: ignored frames from other vehicles ({counts}); "
              f"showing system {view.sysid}", file=sys.stderr)
    if view.time_conflicts:
        print(f"qnav monitor: warning: ignored {view.time_conflicts} frames of system {view.sysid} whose clock "
              f"ran behind (a second process with the same system id?)", file=sys.stderr)
