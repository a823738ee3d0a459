"""The MAVLink shell as a `qnav-robot` extension (firmware_py.plugins.Extension).

Owns the `--mavlink`/`--signing-key` options of `qnav-robot` and attaching
the node to a running `RobotNode`: the node polls once per control tick from
the ticking thread (`node.after_tick`), so MAVLink timeouts resolve within
one control period of robot time and every vehicle call lands between two
ticks. The command line's controller settings win over stored parameters
for this run and are written into the parameter table before the vehicle is
configured, so the ground station sees what is in effect: the control rate
and the cell size always (the command line checked its policy against
them), other settings where they differ from the defaults.
A reboot command reloads the params and the active policy from `--storage`.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
from collections.abc import Callable
from dataclasses import fields

from firmware_py.plugins import ControlNode, UsageError
from firmware_py.vehicle import VehicleConfig

log = logging.getLogger("qnav.mavlink")

# VehicleConfig fields the command line's policy was checked against (firmware_py.policy.config_mismatch)
ALWAYS_FROM_COMMAND_LINE = frozenset({"control_rate_hz", "cell_size_mm"})


class MavlinkExtension:
    """`firmware_py.cli.Extension` for the MAVLink node."""

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        from firmware_py.mavlink.node import add_mavlink_args

        add_mavlink_args(parser)

    def attach(self, node: ControlNode, args: argparse.Namespace) -> Callable[[], None] | None:
        if str(args.mavlink).lower() == "none":
            return None
        from firmware_py.mavlink.node import open_node
        from firmware_py.mavlink.params import PARAMS

        ctrl = node.controller
        clock = node.clock
        cli_cfg = getattr(ctrl, "cfg", None)
        overrides: dict[str, int] = {}
        if cli_cfg is not None:
            defaults = VehicleConfig()
            by_field = {p.field: p.name for p in PARAMS if p.field}
            for f in fields(VehicleConfig):
                value = getattr(cli_cfg, f.name)
                if value != getattr(defaults, f.name) or f.name in ALWAYS_FROM_COMMAND_LINE:
                    overrides[by_field[f.name]] = value

        def reboot_hook() -> tuple[bool, str]:
            if not args.storage:
                return True, ""
            from firmware_py.storage import Storage, boot_policy_candidates

            reasons = []
            for path in boot_policy_candidates(Storage(args.storage)):
                ok, why = ctrl.activate_policy(str(path))
                if ok:
                    return True, ""
                reasons.append(why)
            return (False, "; ".join(reasons)) if reasons else (True, "")

        try:
            shell = open_node(ctrl, args.storage, args.mavlink, clock.now_us(), signing_key=args.signing_key,
                              baud=args.mavlink_baud, reboot_hook=reboot_hook, overrides=overrides,
                              autopilot=getattr(args, "mavlink_autopilot", "generic"))
        except ValueError as exc:  # unreadable key file
            raise UsageError(str(exc)) from None

        closed: list[bool] = []

        def poll(_out: object) -> None:
            if not closed:
                shell.poll(clock.now_us())

        node.after_tick.append(poll)
        log.info("MAVLink node sysid %d on %s%s", shell.node.sysid, args.mavlink,
                 ", signing" if shell.node.signing.key is not None else "")

        def stop() -> None:
            closed.append(True)
            with contextlib.suppress(ValueError):
                node.after_tick.remove(poll)
            shell.close()

        return stop
