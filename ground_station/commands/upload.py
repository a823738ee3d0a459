"""`qnav upload FILE [--activate]`: put a policy on the robot over MAVLink FTP,
prove it arrived byte-exact, and optionally activate it; the verdict comes
from the robot's state (its POLICY_ID and POLICY_CRC_HI/LO parameters plus
the CRC32 of active.qtab), never from one reply. Steps and retries:
docs/mavlink.md, "Uploading a policy".

`--timeout` is the whole upload's budget; of it at most 10 s go to waiting
for the robot's heartbeat.

Two CRCs are named: the "file CRC32" (MAVLink FTP's CRC32 of the whole file,
compared with the robot's copy) and the "policy CRC" (the .qtab header's
own, what the robot reports as POLICY_CRC_HI/LO); `qnav policy inspect`
prints both.

The file is checked with the robot's own policy loader before anything is
sent: what it refuses (a map, a truncated or corrupt .qtab) is refused here
in one line, exit 2 (a MovingAI map is pointed at `qnav map upload`);
`--force` sends it anyway, to see the robot's own refusal.

Exit status: 0 done, 2 bad arguments, 3 refused by the robot (its reason
printed), 4 timeout, no robot or no FTP answer, 5 CRC or policy-id mismatch.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ground_station.errors import CliError

DEFAULT_DEADLINE_S = 300.0
HEARTBEAT_WAIT_S = 10.0


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.mavlink.link import add_link_args

    p = sub.add_parser("upload", help="upload a policy to the robot over MAVLink FTP (and activate it)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    from firmware_py.shipped_policies import policy_file_arg

    p.add_argument("file", type=policy_file_arg, help="the .qtab policy file, or policies:NAME for a shipped one")
    p.add_argument("--activate", action="store_true", help="make it the robot's active policy")
    p.add_argument("--remote", help="path on the robot (default /policies/<file name>)")
    p.add_argument("--attempts", type=int, default=8, help="whole-file put attempts (default %(default)s)")
    p.add_argument("--force", action="store_true",
                   help="send a file the robot's policy loader refuses here (to try the robot's own refusal); "
                        "without it such a file is refused before anything is sent")
    add_link_args(p, timeout_s=DEFAULT_DEADLINE_S,
                  timeout_help=f"give up after this many seconds (default {DEFAULT_DEADLINE_S:g}; "
                               f"of them at most {HEARTBEAT_WAIT_S:g} s waiting for the robot's heartbeat)")
    p.set_defaults(func=run)


def check_policy(path: Path) -> None:
    """CliError, one line, unless `path` is a policy the robot's own loader (firmware_py/policy.py)
    accepts; a MovingAI map is pointed at `qnav map upload`."""
    from firmware_py.policy import PolicyError, load_policy

    try:
        load_policy(path)
    except PolicyError as exc:
        if _looks_like_map(path):
            raise CliError(f"{path}: a MovingAI map, not a policy: `qnav map upload {path}` gives the robot "
                           "its map") from None
        raise CliError(f"{path}: not a policy the robot can load: {exc} (--force sends it anyway)") from None


def _looks_like_map(path: Path) -> bool:
    if path.suffix == ".map":
        return True
    try:
        with open(path, "rb") as f:
            return f.read(5) == b"type "  # a MovingAI header: type octile / height / width / map
    except OSError:
        return False


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ground_station.mavlink.ftp_upload import default_remote, upload_policy
    from ground_station.mavlink.link import LinkError, open_link, warn_foreign

    if not args.file.is_file():
        raise CliError(f"{args.file}: no such file")
    if not args.force:
        check_policy(args.file)
    remote = args.remote or default_remote(args.file)
    size = args.file.stat().st_size
    try:
        link = open_link(args, "upload", connect_timeout_s=min(HEARTBEAT_WAIT_S, args.timeout))
    except LinkError as exc:
        print(f"qnav upload: error: {exc}", file=sys.stderr, flush=True)
        return exc.code
    bar = tqdm(total=size, unit="B", unit_scale=True, desc=f"upload {args.file.name}")

    def progress(frac: float | None) -> None:
        if frac is not None:
            bar.n = int(frac * size)
            bar.refresh()

    try:
        with link:
            res = upload_policy(link, args.file, remote, activate=args.activate, deadline_s=args.timeout,
                                attempts=args.attempts, progress=progress)
    except LinkError as exc:
        bar.close()
        print(f"qnav upload: error: {exc}", file=sys.stderr, flush=True)
        return exc.code
    bar.n = size
    bar.close()
    warn_foreign(link, "upload")
    print(f"uploaded {args.file} -> {remote}: {res.size} B, file CRC32 0x{res.crc:08x} (MAVFTP) verified on "
          f"the robot, {res.put_seconds:.1f} s, {res.put_attempts} attempt(s)")
    if args.activate:
        pid = f"0x{res.policy_id:08x}" if res.policy_id is not None else "unknown"
        pcrc = f"0x{res.policy_crc:08x}" if res.policy_crc is not None else "unknown"
        print(f"activated: policy id {pid}, policy CRC {pcrc}, confirmed by {res.confirmed_by}")
    return 0
