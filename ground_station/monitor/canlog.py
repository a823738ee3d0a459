"""CAN-level facts from a `candump -L` log, for `qnav report FILE.log`.

A candump log line is `(SECONDS) CHANNEL ID#HEXDATA` (can-utils' `-L`
format; `ID#R` is a remote frame). Frames are decoded with the robot's DBC
(firmware_py.can_protocol); the summary holds only what the bus says:

* frames: total, per message name, unknown ids, frames our DBC refuses;
* rates: frames per second of log time (wall time of the recording: in a
  lockstep run the sim's ticks go as fast as the robot answers) and frames
  per SimTick (per control period, whatever the pace);
* commands: MotorCommand count (one per tick answered; a second answer to the
  same tick is counted as `repeated`), how many are zero / non-zero, the
  largest wheel speeds; SimTick counter gaps (lost ticks) and resends (the
  same tick sent again while the lockstep sim waited for a late answer: not a
  new tick, so `sim_ticks` and the per-tick rates leave them out);
* controller: the ControllerHeartbeat states in order (changes only), EStop
  frames engaged/released.
"""

from __future__ import annotations

import re
from collections import Counter
from pathlib import Path

LINE = re.compile(r"^\((\d+(?:\.\d+)?)\)\s+(\S+)\s+([0-9A-Fa-f]{1,8})#(R\d?|[0-9A-Fa-f]*)\s*$")


def is_candump_log(path: str | Path) -> bool:
    """True if the first non-empty line of `path` is a candump -L line."""
    try:
        with open(path, "rb") as f:
            for raw in f:
                line = raw.decode("ascii", errors="replace").strip()
                if line:
                    return LINE.match(line) is not None
    except OSError:
        return False
    return False


def analyse_candump(path: str | Path) -> dict:
    """The summary described in the module docstring."""
    import can

    from firmware_py import can_protocol as cp
    from firmware_py.vehicle import CtrlState

    names: Counter[str] = Counter()
    unknown: Counter[str] = Counter()
    refused = bad_lines = 0
    t_first = t_last = None
    channels: set[str] = set()
    # count: one per controller tick; repeated: a second answer to the same tick (a resent SimTick)
    cmd = {"count": 0, "zero": 0, "nonzero": 0, "max_abs_mm_s": 0, "repeated": 0}
    last_cmd = None
    states: list[list] = []
    estop = {"engaged": 0, "released": 0}
    tick_gaps = tick_resends = 0
    last_tick = None
    with open(path, encoding="ascii", errors="replace") as f:
        for line in f:
            m = LINE.match(line.strip())
            if m is None:
                bad_lines += bool(line.strip())
                continue
            t, channel, ident, data = float(m[1]), m[2], int(m[3], 16), m[4]
            t_first = t if t_first is None else t_first
            t_last = t
            channels.add(channel)
            name = cp.frame_name(ident) if len(m[3]) <= 3 else None
            if name is None:
                unknown[m[3].upper()] += 1
                continue
            if data.startswith("R"):
                refused += 1
                continue
            try:
                _, sig = cp.decode(can.Message(arbitration_id=ident, data=bytes.fromhex(data), is_extended_id=False))
            except (cp.ProtocolError, ValueError):
                refused += 1
                continue
            names[name] += 1
            rel = round(t - t_first, 6)
            if name == "MotorCommand":
                left, right = sig["Cmd_LeftSpeed"], sig["Cmd_RightSpeed"]
                if sig["Cmd_Counter"] == last_cmd:
                    cmd["repeated"] += 1
                    continue
                last_cmd = sig["Cmd_Counter"]
                cmd["count"] += 1
                cmd["zero" if left == 0 and right == 0 else "nonzero"] += 1
                cmd["max_abs_mm_s"] = max(cmd["max_abs_mm_s"], abs(left), abs(right))
            elif name == "ControllerHeartbeat":
                state = CtrlState(sig["Ctrl_State"]).name if sig["Ctrl_State"] in CtrlState._value2member_map_ \
                    else str(sig["Ctrl_State"])
                if not states or states[-1][1] != state:
                    states.append([rel, state])
            elif name == "EStop":
                estop["engaged" if sig["EStop_Engage"] else "released"] += 1
            elif name == "SimTick":
                counter = sig["Tick_Counter"]
                if counter == last_tick:  # the sim resent it (lockstep: its answer was late or lost)
                    tick_resends += 1
                elif last_tick is not None and counter != (last_tick + 1) % cp.TICK_MODULUS:
                    tick_gaps += 1
                last_tick = counter
    duration = (t_last - t_first) if t_first is not None and t_last is not None else 0.0
    ticks = names.get("SimTick", 0) - tick_resends
    per_tick = dict(names, SimTick=ticks, MotorCommand=names.get("MotorCommand", 0) - cmd["repeated"])
    total = sum(names.values()) + sum(unknown.values()) + refused
    return {
        "kind": "candump",
        "file": str(path),
        "channels": sorted(channels),
        "frames": total,
        "duration_s": round(duration, 3),
        "by_name": dict(sorted(names.items())),
        "unknown_ids": dict(sorted(unknown.items())),
        "refused": refused,
        "bad_lines": bad_lines,
        "rate_hz": {n: round(c / duration, 2) for n, c in sorted(names.items())} if duration > 0 else {},
        "per_sim_tick": {n: round(c / ticks, 3) for n, c in sorted(per_tick.items()) if c} if ticks else {},
        "sim_ticks": ticks,
        "sim_tick_resends": tick_resends,
        "sim_tick_gaps": tick_gaps,
        "motor_commands": cmd,
        "controller_states": states,
        "estop": estop,
    }


def text_summary(s: dict) -> list[str]:
    """A few lines for the terminal."""
    c = s["motor_commands"]
    lines = [f"{s['file']}: candump log, {s['frames']} frames on {', '.join(s['channels']) or '-'} "
             f"over {s['duration_s']:.1f} s, {s['sim_ticks']} sim ticks ({s['sim_tick_gaps']} gaps), "
             f"unknown ids {sum(s['unknown_ids'].values())}, refused {s['refused']}",
             f"  motor commands {c['count']} (zero {c['zero']}, non-zero {c['nonzero']}, max {c['max_abs_mm_s']} mm/s), "
             f"e-stop engaged {s['estop']['engaged']}",
             "  controller " + (" -> ".join(st for _, st in s["controller_states"]) or "-")]
    for name, n in s["by_name"].items():
        lines.append(f"  {name:<20} {n:>7}  {s['rate_hz'].get(name, 0):8.1f}/s  "
                     f"{s['per_sim_tick'].get(name, 0):6.3f}/tick")
    return lines


def write_candump(src: str | Path, dst: str | Path, channel: str = "can0") -> int:
    """Copy a python-can log (`.blf`, `.asc`, ...) to a `candump -L` file (`(SECONDS) CHANNEL
    ID#HEXDATA`, what `cantools decode`, `canplayer` and `qnav report` read), written to a
    temporary name and moved into place. Returns the frame count."""
    import os

    import can

    dst = Path(dst)
    tmp = dst.with_name(f".{dst.name}.partial")
    n = 0
    with open(tmp, "w") as out:
        for msg in can.LogReader(str(src)):
            if msg.is_error_frame:
                continue
            ident = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
            data = "R" if msg.is_remote_frame else bytes(msg.data).hex().upper()
            out.write(f"({msg.timestamp:.6f}) {channel} {ident}#{data}\n")
            n += 1
    os.replace(tmp, dst)
    return n
