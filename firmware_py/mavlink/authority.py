"""Who may steer the robot over MAVLink: the operator's GCS only (ArduPilot's SYSID_MYGCS).

`ControlGate` takes every input that moves the robot or changes what it will do only from the system
id SYSID_MYGCS (0: any) and only when addressed to the robot; it counts the refusals per (system,
message kind) and summarises them at most once a second (`summary`), so a flood costs a dictionary
update each. Which inputs, and why: docs/mavlink.md, "Who may steer: SYSID_MYGCS".
"""

from __future__ import annotations

from firmware_py.mavlink.dialect import mavlink2

M = mavlink2

CONTROL_MSGS = frozenset({
    "MANUAL_CONTROL", "RC_CHANNELS_OVERRIDE", "SET_MODE", "SET_POSITION_TARGET_LOCAL_NED",
    "SET_POSITION_TARGET_GLOBAL_INT", "MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ITEM",
    "MISSION_CLEAR_ALL", "MISSION_SET_CURRENT", "PARAM_SET",
})
COMMAND_MSGS = frozenset({"COMMAND_LONG", "COMMAND_INT"})
# commands that only ask for data: any system may send them (a second monitor, a log tool)
OPEN_COMMANDS = frozenset({
    M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAV_CMD_GET_MESSAGE_INTERVAL, M.MAV_CMD_REQUEST_MESSAGE,
    M.MAV_CMD_REQUEST_PROTOCOL_VERSION, M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, M.MAV_CMD_GET_HOME_POSITION,
})
SUMMARY_PERIOD_US = 1_000_000
MAX_KEYS = 64  # distinct (system, kind) counters kept between summaries; more are counted in `other`


def is_control(msg: mavlink2.MAVLink_message, kind: str) -> bool:
    """True for the inputs the gate guards (module doc)."""
    if kind in CONTROL_MSGS:
        return True
    return kind in COMMAND_MSGS and getattr(msg, "command", None) not in OPEN_COMMANDS


def target_of(msg: mavlink2.MAVLink_message) -> int | None:
    """The message's target system (MANUAL_CONTROL calls it `target`); None when it has none."""
    target = getattr(msg, "target_system", None)
    return getattr(msg, "target", None) if target is None else target


class ControlGate:
    """Decides, counts and summarises; pure (no I/O, the caller's clock)."""

    def __init__(self) -> None:
        self._since: dict[tuple[int, str], int] = {}  # refusals since the last summary
        self._other = 0
        self._next_summary_us: int | None = None

    def refuse(self, msg: mavlink2.MAVLink_message, kind: str, my_gcs: int, now_us: int) -> str | None:
        """None when `msg` may act; otherwise why not (and the refusal is counted)."""
        if not is_control(msg, kind):
            return None
        src = msg.get_srcSystem()
        if target_of(msg) == 0:
            why = "addressed to every system (target 0)"
        elif my_gcs != 0 and src != my_gcs:
            why = f"system {src} is not SYSID_MYGCS {my_gcs}"
        else:
            return None
        key = (src, kind)
        if key in self._since or len(self._since) < MAX_KEYS:
            self._since[key] = self._since.get(key, 0) + 1
        else:
            self._other += 1
        if self._next_summary_us is None:
            self._next_summary_us = now_us  # the first refusal is reported at once
        return why

    def summary(self, now_us: int, my_gcs: int) -> str | None:
        """At most once a SUMMARY_PERIOD_US: one line naming who was refused what, or None."""
        if not self._since and not self._other:
            return None
        if self._next_summary_us is not None and now_us < self._next_summary_us:
            return None
        parts = [f"sys {src} {kind} x{n}" for (src, kind), n in sorted(self._since.items())[:6]]
        more = len(self._since) - len(parts)
        if more > 0 or self._other:
            parts.append(f"+{more + self._other} more")
        self._since.clear()
        self._other = 0
        self._next_summary_us = now_us + SUMMARY_PERIOD_US
        who = "any system" if my_gcs == 0 else f"SYSID_MYGCS {my_gcs}"
        return f"control refused (only {who}, addressed): " + ", ".join(parts)
