"""The MAVLink shell as a `qnav-robot` extension (firmware_py.plugins.Extension): the `--mavlink`
and `--signing-key` options, and attaching the node to a running `RobotNode` (its own link thread,
a storage worker for the parameter saves, the command line's controller settings written into the
parameter table before the vehicle is configured). Details: docs/mavlink.md, "Node structure".
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import logging
from collections.abc import Callable
from dataclasses import fields
from typing import Any

from firmware_py.plugins import ControlNode, UsageError
from firmware_py.vehicle import VehicleConfig

log = logging.getLogger("qnav.mavlink")

# VehicleConfig fields the command line's policy was checked against (firmware_py.policy.config_mismatch)
ALWAYS_FROM_COMMAND_LINE = frozenset({"control_rate_hz", "cell_size_mm"})


class MavlinkExtension:
    """`firmware_py.cli.Extension` for the MAVLink node."""

    def __init__(self) -> None:
        self._stats: Callable[[], dict[str, Any]] | None = None

    def stats(self) -> dict[str, Any]:
        """Link thread and storage worker counters of the attached node ({} if none)."""
        return self._stats() if self._stats is not None else {}

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        from firmware_py.mavlink.node import add_mavlink_args

        add_mavlink_args(parser)

    def attach(self, node: ControlNode, args: argparse.Namespace) -> Callable[[], None] | None:
        if str(args.mavlink).lower() == "none":
            return None
        from firmware_py.mavlink.node import open_node
        from firmware_py.mavlink.params import PARAMS
        from firmware_py.mavlink.telemetry import DEFAULT_AUTOPILOT

        ctrl = node.controller
        clock = node.clock
        cli_cfg = getattr(ctrl, "cfg", None)
        overrides: dict[str, int] = {}
        if cli_cfg is not None:
            defaults = VehicleConfig()
            by_field = {p.field: p.name for p in PARAMS if p.field}
            overrides = {by_field[f.name]: getattr(cli_cfg, f.name) for f in fields(VehicleConfig)
                         if getattr(cli_cfg, f.name) != getattr(defaults, f.name) or f.name in ALWAYS_FROM_COMMAND_LINE}

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
                              autopilot=getattr(args, "mavlink_autopilot", DEFAULT_AUTOPILOT))
        except ValueError as exc:  # unreadable key file
            raise UsageError(str(exc)) from None
        except OSError as exc:  # the port taken, no such serial device, no permission
            why = exc.strerror or str(exc)
            hint = " (another program listens there: another qnav-robot?)" if exc.errno == errno.EADDRINUSE else ""
            raise UsageError(f"--mavlink {args.mavlink}: {why}{hint}") from None

        from firmware_py.mavlink.link_thread import LinkThread, StorageWorker

        worker = StorageWorker()
        shell.node.params.deferred = worker
        switch_us = getattr(args, "gil_switch_us", None)
        link = LinkThread(shell, clock, lambda: int(getattr(ctrl, "cfg", VehicleConfig()).control_period_us),
                          switch_interval_s=switch_us / 1e6 if switch_us else None)
        node.after_tick.append(link.on_tick)
        link.start()

        def stats() -> dict[str, Any]:
            return {**link.stats(), "gcs_last_heartbeat_us": shell.node.gcs_last_heartbeat_us,
                    "failsafe_since_us": shell.node.failsafe_since_us, "storage_saves": worker.done, "storage_coalesced": worker.coalesced,
                    "storage_dropped": worker.dropped, "storage_errors": worker.errors,
                    "param_save_errors": shell.node.params.save_errors,
                    "foreign_gcs_heartbeats": shell.node.foreign_gcs_heartbeats}

        self._stats = stats
        log.info("MAVLink node sysid %d on %s%s", shell.node.sysid, args.mavlink,
                 ", signing" if shell.node.signing.key is not None else "")

        def stop() -> None:
            with contextlib.suppress(ValueError):
                node.after_tick.remove(link.on_tick)
            link.stop()
            worker.close()
            shell.close()

        return stop
