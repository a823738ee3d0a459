"""`qnav param list|get NAME|set NAME VALUE`: the robot's parameters over MAVLink.

`set` waits for the robot's PARAM_VALUE echo and fails (exit 3) with the
robot's reason when it kept another value (out of range, read-only,
unknown); no answer -> exit 4. The robot stores a set value atomically and
keeps it across reboots. `list` prints each parameter's description, units
and range beside its value, read from the robot's own parameter metadata
(`/metadata/parameters.json` over MAVLink FTP, the file its
COMPONENT_METADATA points a ground station at). POLICY_ID and POLICY_CRC are
32-bit ids that float32 on the wire rounds: `get` and `list` print them
exact, in hex, from their _HI/_LO halves (as `qnav export` and the monitor
do). See docs/mavlink.md for the table.
"""

from __future__ import annotations

import argparse
import json

from ground_station.commands import add_actions


def add_subparser(sub: argparse._SubParsersAction) -> None:
    from ground_station.mavlink.link import add_link_args

    verbs = add_actions(sub, "param", "list, read or set robot parameters (MAVLink)", __doc__, "verb", "VERB")
    lst = verbs.add_parser("list", help="print every parameter")
    lst.add_argument("--json", action="store_true", help="print as a JSON object")
    lst.add_argument("--no-descriptions", action="store_true",
                     help="values only: do not read the robot's parameter metadata (one FTP read)")
    get = verbs.add_parser("get", help="print one parameter")
    get.add_argument("name", metavar="NAME")
    st = verbs.add_parser("set", help="set one parameter and verify the echo")
    st.add_argument("name", metavar="NAME")
    st.add_argument("value", metavar="VALUE")
    for v in (lst, get, st):
        add_link_args(v)
        v.set_defaults(func=run)


def _fmt(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


EXACT_IDS = ("POLICY_ID", "POLICY_CRC")  # 32-bit ids: float32 on the wire rounds them; exact from _HI/_LO


def _exact(name: str, params: dict[str, float | None]) -> int | None:
    """POLICY_ID and POLICY_CRC: float32 on the wire; their exact value from the 16-bit halves
    (None for another parameter, or a robot that sends no halves)."""
    hi, lo = params.get(name + "_HI"), params.get(name + "_LO")
    if name not in EXACT_IDS or hi is None or lo is None:
        return None
    return (int(hi) << 16) | int(lo)


def _shown(name: str, value: float, params: dict[str, float | None]) -> str:
    """A value as `param get` and `param list` both print it: an id exact, in hex, as qnav export,
    qnav upload and the monitor print it; anything else as a number."""
    exact = _exact(name, params)
    return f"0x{exact:08x}" if exact is not None else _fmt(value)


def _described(entry: dict | None) -> str:
    if not entry:
        return ""
    units = f" {entry['units']}" if entry.get("units") else ""
    return f"  {entry.get('shortDesc', '')} [{entry.get('min')}..{entry.get('max')}{units}]"


def robot_parameter_metadata(link) -> dict[str, dict]:
    """name -> the robot's metadata entry (firmware_py/mavlink/metadata.py), {} if it serves none."""
    from firmware_py.mavlink.metadata import PARAMETER_FILE
    from ground_station.mavlink.link import LinkError
    from ground_station.mavlink.robot_map import read_robot_file

    try:
        data = read_robot_file(link, PARAMETER_FILE)
        return {p["name"]: p for p in json.loads(data)["parameters"]} if data else {}
    except (ValueError, KeyError, TypeError, LinkError):  # not qnav's metadata, or no FTP: values only
        return {}


def run(args: argparse.Namespace) -> int:
    from ground_station.errors import CliError
    from ground_station.mavlink.link import run_on_link

    name = getattr(args, "name", None)
    if name is not None and not 0 < len(name) <= 16:
        raise CliError(f"parameter name must be 1-16 characters, got {name!r}")
    if args.verb == "set":
        try:
            value = float(args.value)
        except ValueError as exc:
            raise CliError(f"VALUE must be a number, got {args.value!r}") from exc

    def body(link) -> int:
        if args.verb == "list":
            params = link.param_list()
            values: dict[str, float | None] = dict(params)
            if args.json:  # numbers, the ids exact
                print(json.dumps({k: _exact(k, values) if _exact(k, values) is not None
                                  else int(v) if float(v).is_integer() else v for k, v in params.items()}, indent=1))
            else:
                meta = {} if args.no_descriptions else robot_parameter_metadata(link)
                for k, v in params.items():
                    print(f"{k:<16} {_shown(k, v, values):>11}{_described(meta.get(k))}")
        elif args.verb == "get":
            assert name is not None
            got = link.param_get(name)
            halves: dict[str, float | None] = {}
            if name in EXACT_IDS:
                halves = link.read_params([name + "_HI", name + "_LO"], budget_s=min(args.timeout, 3.0))
            print(f"{name} {_shown(name, got, halves)}")
        else:
            print(f"{name} {_fmt(link.param_set(name, value))}")
        return 0

    return run_on_link(args, f"param {args.verb}", body)
