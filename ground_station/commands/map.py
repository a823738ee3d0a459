"""`qnav map upload NAME|FILE.map`: give the robot its own map over MAVLink FTP.

The map is the robot's, apart from its policy (as nav2's map server is apart
from its controller): the robot localises and plans on the map it was given,
and keeps it across reboots (/maps/active.map in its storage; the one before
it is /maps/last_good.map). The file goes up as MovingAI text, is verified
by CRC and renamed onto /maps/active.map; the robot parses it with its own
cell size (CELL_SIZE_MM), refuses it when its policy is tied to another map
(a cell table, naming both) or it is driving, builds the map's localiser off
its control tick and swaps it in. A refusal exits 3 with the robot's reason;
the old map stays. A sector or sector-memory policy runs on whichever map
the robot has.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from ground_station.commands import add_actions


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.mavlink.link import add_link_args

    inner = add_actions(sub, "map", "the robot's own map (MAVLink FTP): upload", __doc__, "map_command")
    up = inner.add_parser("upload", help="put a map on the robot and make it the one it drives on",
                          description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    up.add_argument("map", metavar="NAME|FILE.map", help="a built-in map, a generator spec or a MovingAI .map file")
    add_link_args(up)
    up.set_defaults(func=run_upload)


def run_upload(args: argparse.Namespace) -> int:
    from ground_station.errors import CliError
    from ground_station.maps import MapError, load_map, write_map
    from ground_station.mavlink.ftp_upload import put_plain_file, upload_map
    from ground_station.mavlink.link import run_on_link
    from ground_station.mavlink.robot_map import MAP_TARGETS, targets_file

    try:
        gm = load_map(args.map)
    except (MapError, OSError, ValueError) as exc:
        raise CliError(f"map {args.map}: {exc}") from None
    with tempfile.TemporaryDirectory() as tmp:
        local = Path(tmp) / "upload.map"
        write_map(local, gm)  # MovingAI text, whatever it was given as

        def body(link) -> int:
            res = upload_map(link, local, deadline_s=max(args.timeout, 10.0))
            print(f"map {gm.name} ({gm.width}x{gm.height} cells) active on the robot: {res.size} B, "
                  f"CRC32 0x{res.crc:08x}, confirmed by {res.confirmed_by}")
            # its targets beside it (tied to the map's CRC32), so that missions and goals by target name
            # read them from the robot (mavlink/robot_map.py); the robot itself does not use them
            sidecar = Path(tmp) / "targets.json"
            sidecar.write_bytes(targets_file(local.read_bytes(), gm.name, gm.targets))
            put_plain_file(link, sidecar, MAP_TARGETS, deadline_s=max(args.timeout, 10.0))
            if gm.targets:
                print(f"targets {', '.join(gm.targets)} kept beside it ({MAP_TARGETS})")
            return 0

        return run_on_link(args, "map upload", body)
