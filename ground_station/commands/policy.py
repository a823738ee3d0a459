"""`qnav policy inspect FILE...`: validate `.qtab` files and print their
headers. `qnav policy upgrade OLD.qtab [--out NEW.qtab] --control-period-us
US [--map NAME]`: migrate a version 1.x file to the current format. `qnav
policy attach-map FILE --map NAME [--out NEW.qtab]`: put the training map's
cells into the file (metadata `map_grid`) for the robot's localiser. `qnav
policy revert [--mavlink URL]`: make the robot's last good policy its active
one again, over MAVLink FTP (docs/deploy.md, "Update a policy").

inspect: one line per file (a JSON object per line with `--json`: `file`,
`valid`, `error` and the header fields, among them `control_period_us` and
`map_geometry`). Exit status 0 only when every file is valid, 2 otherwise.
Validation is the robot's own loader (firmware_py.policy).

Two CRCs, named alike in `qnav upload`: the "policy CRC" is the .qtab's own
header field (what the robot reports as POLICY_CRC_HI/LO); the "file CRC32"
is MAVLink FTP's CRC32 of the whole file (CalcFileCRC32: zlib's polynomial,
no final xor, so it differs from `zlib.crc32`/`crc32(1)` of the same bytes),
what the upload compares with the robot's copy.

upgrade: version 1.x files record neither the control period nor the map
geometry they were trained for, and the robot refuses them. `upgrade` writes
them into the header (atomically, over OLD unless --out is given) and copies
everything else byte for byte, so the table, policy id and creation time are
unchanged. A cell policy's geometry is its grid; a sector policy's is the
training map's: --map, else the map named in the file's metadata. Every
policy trained so far ran the twin at robot_spec.CONTROL_PERIOD_US (50000
us).

revert: the robot keeps the policy it ran before the last activation in
/policies/last_good.qtab (read-only over FTP). revert reads it, puts it back
as /policies/revert.qtab and renames that onto /policies/active.qtab, so the
robot validates and activates it as any `qnav upload --activate` (and
refuses it the same way, e.g. while driving); the policy it ran becomes the
last good one, so a second revert goes forward again. It prints the policy
ids before and after; the verdict is the robot's POLICY_ID/POLICY_CRC
parameters and the CRC32 of its active.qtab
(ground_station/mavlink/policy_revert.py). Exit status as `qnav upload`: 0
done, 2 bad arguments, 3 refused (no last good policy, already running it,
or the robot's refusal, printed), 4 timeout or no robot, 5 CRC or policy-id
mismatch.
"""

from __future__ import annotations

import argparse
import json
import struct

from firmware_py import robot_spec
from ground_station.commands import add_actions
from ground_station.errors import CliError

REVERT_DEADLINE_S = 300.0  # as `qnav upload`
REVERT_HEARTBEAT_WAIT_S = 10.0


def add_subparser(sub: argparse._SubParsersAction) -> None:
    inner = add_actions(sub, "policy", "inspect, upgrade and map .qtab policy files; revert the robot's",
                        __doc__, "policy_command")
    ins = inner.add_parser("inspect", help="validate policy files and print their headers",
                           description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ins.add_argument("files", nargs="+", metavar="FILE", help=".qtab file(s), or policies:NAME (shipped)")
    ins.add_argument("--json", action="store_true", help="one JSON object per line")
    ins.add_argument("--sensors", type=int, default=robot_spec.SENSOR_COUNT,
                     help="the robot's range-sensor count to validate against (default %(default)s)")
    ins.set_defaults(func=run)
    up = inner.add_parser("upgrade", help="migrate a version 1.x file (records control period and map geometry)",
                          description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    up.add_argument("file", metavar="OLD.qtab", help="version 1.x policy file")
    up.add_argument("--out", metavar="NEW.qtab", help="where to write (default: replace OLD.qtab atomically)")
    up.add_argument("--control-period-us", type=int, required=True, metavar="US",
                    help=f"control period the policy was trained for (the twin's: {robot_spec.CONTROL_PERIOD_US})")
    up.add_argument("--map", metavar="NAME|PATH",
                    help="training map (sector policies; default: the map in the file's metadata)")
    up.set_defaults(func=run_upgrade)
    am = inner.add_parser("attach-map", help="carry the training map's cells in the file (for the localiser)",
                          description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    am.add_argument("file", metavar="FILE.qtab", help="a valid policy file")
    am.add_argument("--map", metavar="NAME|PATH",
                    help="the training map (default: the map named in the file's metadata)")
    am.add_argument("--out", metavar="NEW.qtab", help="where to write (default: replace FILE atomically)")
    am.set_defaults(func=run_attach_map)
    from ground_station.mavlink.link import add_link_args

    rv = inner.add_parser("revert", help="make the robot's last good policy active again (MAVLink FTP)",
                          description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    rv.add_argument("--attempts", type=int, default=8, help="whole-file put attempts (default %(default)s)")
    add_link_args(rv, timeout_s=REVERT_DEADLINE_S,
                  timeout_help=f"give up after this many seconds (default {REVERT_DEADLINE_S:g}; of them at most "
                               f"{REVERT_HEARTBEAT_WAIT_S:g} s waiting for the robot's heartbeat)")
    rv.set_defaults(func=run_revert)


def describe(path: str, expect_sensors: int = robot_spec.SENSOR_COUNT) -> dict:
    """Validation result and header of one file as a JSON-able dict."""
    from firmware_py.policy import PolicyError, load_policy
    from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec
    from firmware_py.storage import ftp_crc32

    try:
        resolved = resolve_policy_spec(path)
        pol = load_policy(resolved, expect_sensors=expect_sensors)
        with open(resolved, "rb") as f:
            file_crc = ftp_crc32(f.read())
    except (PolicyError, ShippedPolicyError) as exc:
        return {"file": path, "valid": False, "error": str(exc)}
    from firmware_py.needs import NEEDS_KEY, needs_of

    # what the policy needs of the robot (firmware_py.needs): its record, else the built-in robot's
    recorded = isinstance(pol.metadata, dict) and NEEDS_KEY in pol.metadata
    return {"file": path, "valid": True, "error": None, **pol.header(), "file_crc32": f"0x{file_crc:08x}",
            "robot_needs": needs_of(pol), "robot_needs_recorded": recorded}


def _line(d: dict) -> str:
    if not d["valid"]:
        return f"{d['file']}: INVALID: {d['error']}"
    enc = d["encoder"]  # the kind's own encoder fields, as its to_dict() names them
    geo = " ".join([d["kind"], *(f"{k}={json.dumps(v, separators=(',', ':'))}" for k, v in enc.items() if k != "kind")])
    if d.get("goals"):
        geo += f" goals={json.dumps(d['goals'], separators=(',', ':'))} cell_mm={d['cell_mm']}"
    mg = d["map_geometry"]
    geo += f" period_us={d['control_period_us']} map={mg['width']}x{mg['height']}x{mg['cell_mm']}mm"
    grid = d.get("map_grid")
    geo += f" map_grid={grid['occupied_cells']}/{grid['width'] * grid['height']} occupied" if grid else " map_grid=none"
    geo += " local_planner=on" if d.get("local_planner") else ""
    meta = d["metadata"]
    extra = " ".join(f"{k}={json.dumps(meta[k])}" for k in ("map", "targets", "steps") if k in meta)
    scale = "per-state" if d["per_state_scales"] else f"{d['scale']:.6g}"
    return (f"{d['file']}: valid v{d['format_version']} {geo} {d['dtype']} "
            f"{d['n_states']}x{d['n_actions']} scale={scale} id={d['policy_id']} "
            f"policy CRC {d['crc32']} file CRC32 {d['file_crc32']} "
            f"created={d['created_utc']} bytes={d['bytes']}" + (f" {extra}" if extra else "") + _needs(d))


def _needs(d: dict) -> str:
    """The robot_needs record as the line's last part (firmware_py.needs.describe)."""
    from firmware_py.needs import describe as describe_needs

    if "robot_needs" not in d:
        return ""
    where = "" if d.get("robot_needs_recorded") else " (no record: the built-in robot)"
    return f" robot_needs{where}: " + "; ".join(describe_needs(d["robot_needs"]))


def run(args: argparse.Namespace) -> int:
    results = [describe(f, args.sensors) for f in args.files]
    for d in results:
        print(json.dumps(d, sort_keys=True) if args.json else _line(d))
    return 0 if all(d["valid"] for d in results) else 2


def _read(path: str) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError as exc:
        raise CliError(f"cannot read {path}: {exc.strerror or exc}") from None


def _replace(out: str, data: bytes) -> str:
    """Write `data` to `out` atomically (a crash leaves the old file); returns `out`."""
    from firmware_py.atomic import atomic_write

    try:
        atomic_write(out, data)
    except OSError as exc:
        raise CliError(f"cannot write {out}: {exc.strerror or exc}") from None
    return out


def run_upgrade(args: argparse.Namespace) -> int:
    from firmware_py.policy import HEADER_V1, MapGeometry, PolicyError, upgrade_policy
    from ground_station.learn.export import geometry_of_map

    data = _read(args.file)
    geometry: MapGeometry | None = None
    # a sector 1.x file needs its training map; anything else goes straight to upgrade_policy's checks
    is_old_sector = len(data) >= HEADER_V1.size and data[4] == 1 and data[12] == 2  # major, kind bytes
    if args.map or is_old_sector:
        map_name = args.map or _metadata_map(data)
        if not map_name:
            raise CliError(f"{args.file}: sector policy names no training map in its metadata; pass --map")
        try:
            geometry = geometry_of_map(map_name)
        except ValueError as exc:
            raise CliError(str(exc)) from None
    try:
        new = upgrade_policy(data, args.control_period_us, geometry)
    except PolicyError as exc:
        raise CliError(f"{args.file}: {exc}") from None
    out = _replace(args.out or args.file, new)
    print(json.dumps(describe(out), sort_keys=True))
    return 0


def run_attach_map(args: argparse.Namespace) -> int:
    from firmware_py.policy import PolicyError, load_policy
    from ground_station.learn.export import attach_map

    data = _read(args.file)
    try:
        name = args.map or load_policy(data).metadata.get("map")
    except PolicyError as exc:
        raise CliError(f"{args.file}: {exc}") from None
    if not isinstance(name, str) or not name:
        raise CliError(f"{args.file}: names no training map in its metadata; pass --map")
    try:
        new = attach_map(data, name)
    except ValueError as exc:
        raise CliError(f"{args.file}: {exc}") from None
    out = _replace(args.out or args.file, new)
    print(_line(describe(out)))
    return 0


def run_revert(args: argparse.Namespace) -> int:
    """`qnav policy revert`: one line before, one after; a LinkError is one line and its exit code."""
    import sys

    from ground_station.mavlink.link import LinkError, open_link, warn_foreign
    from ground_station.mavlink.policy_revert import LAST_GOOD_POLICY, revert_policy

    def hexid(v: int | None) -> str:
        return "unknown" if v is None else f"0x{v:08x}"

    def show(before: int | None, last_good: int | None) -> None:
        running = "none" if before == 0 else hexid(before)
        print(f"before: the robot runs policy {running}; {LAST_GOOD_POLICY} holds {hexid(last_good)}", flush=True)

    try:
        link = open_link(args, "policy revert", connect_timeout_s=min(REVERT_HEARTBEAT_WAIT_S, args.timeout))
        with link:
            res = revert_policy(link, deadline_s=args.timeout, attempts=args.attempts, on_read=show)
    except LinkError as exc:
        print(f"qnav policy revert: error: {exc}", file=sys.stderr, flush=True)
        return exc.code
    warn_foreign(link, "policy revert")
    up = res.upload
    print(f"after: the robot runs policy {hexid(up.policy_id)} (policy CRC {hexid(up.policy_crc)}), "
          f"confirmed by {up.confirmed_by}")
    return 0


def _metadata_map(data: bytes) -> str | None:
    """The training map a version 1.x file's metadata names, if it can be read."""
    from firmware_py.policy import HEADER_V1

    try:
        fields = HEADER_V1.unpack_from(data, 0)
        header_size, enc_len, meta_len = fields[3], fields[12], fields[13]
        off = header_size + enc_len
        meta = json.loads(data[off:off + meta_len].decode("utf-8")) if meta_len else {}
    except (struct.error, UnicodeDecodeError, ValueError):
        return None
    name = meta.get("map") if isinstance(meta, dict) else None
    return name if isinstance(name, str) else None
