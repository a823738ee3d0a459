"""`qnav policy inspect FILE...`: validate `.qtab` files and print their headers.

One line per file (a JSON object per line with `--json`: `file`, `valid`,
`error` and the header fields). Exit status 0 only when every file is valid,
2 otherwise. Validation is the robot's own loader (firmware_py.policy).
"""

from __future__ import annotations

import argparse
import json

from firmware_py import robot_spec


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("policy", help="inspect .qtab policy files", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    inner = p.add_subparsers(dest="policy_command", metavar="ACTION")
    inner.required = True
    ins = inner.add_parser("inspect", help="validate policy files and print their headers",
                           description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ins.add_argument("files", nargs="+", metavar="FILE", help=".qtab file(s), or policies:NAME (shipped)")
    ins.add_argument("--json", action="store_true", help="one JSON object per line")
    ins.add_argument("--sensors", type=int, default=robot_spec.SENSOR_COUNT,
                     help="the robot's range-sensor count to validate against (default %(default)s)")
    ins.set_defaults(func=run)


def describe(path: str, expect_sensors: int = robot_spec.SENSOR_COUNT) -> dict:
    """Validation result and header of one file as a JSON-able dict."""
    from firmware_py.policy import PolicyError, load_policy
    from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec

    try:
        pol = load_policy(resolve_policy_spec(path), expect_sensors=expect_sensors)
    except (PolicyError, ShippedPolicyError) as exc:
        return {"file": path, "valid": False, "error": str(exc)}
    return {"file": path, "valid": True, "error": None, **pol.header()}


def _line(d: dict) -> str:
    if not d["valid"]:
        return f"{d['file']}: INVALID: {d['error']}"
    enc = d["encoder"]
    if d["kind"] == "cell":
        geo = f"cell {enc['width']}x{enc['height']} goals={d['goals']} cell_mm={d['cell_mm']}"
    else:
        geo = (f"sector bearing_sectors={enc['bearing_sectors']} sensors={enc['sensors']} "
               f"edges_mm={enc['range_edges_mm']}")
    meta = d["metadata"]
    extra = " ".join(f"{k}={json.dumps(meta[k])}" for k in ("map", "targets", "steps") if k in meta)
    scale = "per-state" if d["per_state_scales"] else f"{d['scale']:.6g}"
    return (f"{d['file']}: valid v{d['format_version']} {geo} {d['dtype']} "
            f"{d['n_states']}x{d['n_actions']} scale={scale} id={d['policy_id']} crc={d['crc32']} "
            f"created={d['created_utc']} bytes={d['bytes']}" + (f" {extra}" if extra else ""))


def run(args: argparse.Namespace) -> int:
    results = [describe(f, args.sensors) for f in args.files]
    for d in results:
        print(json.dumps(d, sort_keys=True) if args.json else _line(d))
    return 0 if all(d["valid"] for d in results) else 2
