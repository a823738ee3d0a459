"""Where the monitor's messages come from: a live MAVLink link or a tlog.

Both sources have the same small surface, polled without blocking from the
dashboard's timer or the `--plain` loop:

* `poll(limit)` -> list of (message, t) received since the last call, `t` in
  the source's time base (wall seconds live, the recording's stamps in a
  replay);
* `now()` -> current time in that base (heartbeat age is measured on it);
* `finished` -> a replay reached its end;
* `send_command(kind)` -> "arm" | "disarm" | "hold" as COMMAND_LONG (live
  only; a replay refuses with a one-line reason).

`run_plain` is the `--plain` loop: one status line per second of source time.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import IO, Protocol

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink is imported: MAVLink 2 from the start

from pymavlink import mavutil  # noqa: E402

from firmware_py.mavlink.dialect import mavlink2 as mavlink  # noqa: E402
from firmware_py.vehicle import Mode  # noqa: E402
from ground_station.monitor.model import POLICY_ID_HALVES, VehicleView  # noqa: E402

HEARTBEAT_PERIOD_S = 1.0
COMMANDS = ("arm", "disarm", "hold")


class MessageSource(Protocol):
    finished: bool

    def poll(self, limit: int = 2000) -> list[tuple[object, float]]: ...
    def now(self) -> float: ...
    def send_command(self, kind: str, target: tuple[int, int]) -> str: ...
    def close(self) -> None: ...


def command_long_args(kind: str) -> tuple[int, list[float]]:
    """(MAV_CMD, params 1-7) for a dashboard key."""
    if kind in ("arm", "disarm"):
        return mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [int(kind == "arm"), 0, 0, 0, 0, 0, 0]
    if kind == "hold":
        return mavlink.MAV_CMD_DO_SET_MODE, [mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, Mode.HOLD, 0, 0, 0, 0, 0]
    raise ValueError(f"unknown command {kind!r}; expected one of {', '.join(COMMANDS)}")


class LiveSource:
    """The ground-station link to the robot (`ground_station.mavlink.link.Link`, which owns signing
    and the session .tlog). Sends a GCS heartbeat each second so the robot's GCS failsafe stays
    quiet while we watch, and asks for the read-only POLICY_ID_HI/LO parameters every few seconds
    (it changes when a policy is activated). Never blocks: command ACKs arrive via `poll`."""

    finished = False
    POLICY_POLL_S = 5.0

    def __init__(self, link, clock=time.time) -> None:
        self.link = link
        self.conn = link.conn
        self._clock = clock
        self._next_hb = 0.0
        self._next_param = 0.0

    def now(self) -> float:
        return self._clock()

    def poll(self, limit: int = 2000) -> list[tuple[object, float]]:
        now = self.now()
        if now >= self._next_hb:
            self.link.send_heartbeat()
            self._next_hb = now + HEARTBEAT_PERIOD_S
        if now >= self._next_param and self.conn.target_system:
            for name in POLICY_ID_HALVES:  # exact, unlike POLICY_ID's float32
                self.conn.mav.param_request_read_send(self.conn.target_system, self.conn.target_component or 1,
                                                      name.encode(), -1)
            self._next_param = now + self.POLICY_POLL_S
        out: list[tuple[object, float]] = []
        while len(out) < limit:
            msg = self.conn.recv_match(blocking=False)
            if msg is None:
                break
            if msg.get_type() != "BAD_DATA":
                out.append((msg, self.now()))
        return out

    def send_command(self, kind: str, target: tuple[int, int]) -> str:
        cmd, params = command_long_args(kind)
        self.conn.mav.command_long_send(target[0], target[1], cmd, 0, *params)
        return f"sent {kind} (COMMAND_LONG {mavlink.enums['MAV_CMD'][cmd].name})"

    def close(self) -> None:
        self.link.close()


def open_live(url: str, tlog=None, signing_key: str | None = None, target_system: int | None = None,
              source: tuple[int, int] | None = None) -> LiveSource:
    """Open the link to the robot on `url` (a pymavlink connection string).
    `tlog`: a path, None for a new session log under runs/tlogs/, False for none;
    `source`: our (system, component) ids (default the link's GCS_SYSID, GCS_COMPID)."""
    from ground_station.mavlink.link import GCS_COMPID, GCS_SYSID, Link

    sysid, compid = source or (GCS_SYSID, GCS_COMPID)
    return LiveSource(Link(url, signing_key=signing_key, tlog=tlog, name="monitor", target_system=target_system,
                           source_system=sysid, source_component=compid))


class ReplaySource:
    """A .tlog played back at `speed` x the recorded pace (the stamps are the
    tlog's own 8-byte µs timestamps). `speed=0` replays as fast as polled."""

    def __init__(self, path: str, speed: float = 1.0, clock=time.monotonic) -> None:
        if not os.path.isfile(path):
            raise FileNotFoundError(f"no such tlog: {path}")
        self.path = path
        self.speed = speed
        self._clock = clock
        self._log = mavutil.mavlogfile(path, robust_parsing=True)
        self._pending = None
        self._t0_log: float | None = None
        self._t0_wall: float | None = None
        self._t_log = 0.0
        self._read_next()
        self.finished = self._pending is None

    def _read_next(self) -> None:
        msg = self._log.recv_msg()
        while msg is not None and msg.get_type() == "BAD_DATA":
            msg = self._log.recv_msg()
        self._pending = msg

    def now(self) -> float:
        if self._t0_log is None:
            return self._pending._timestamp if self._pending is not None else 0.0
        if self.speed <= 0 or self.finished:
            return self._t_log
        return self._t0_log + (self._clock() - self._t0_wall) * self.speed

    def poll(self, limit: int = 2000) -> list[tuple[object, float]]:
        out: list[tuple[object, float]] = []
        if self._pending is None:
            self.finished = True
            return out
        if self._t0_log is None:
            self._t0_log = self._pending._timestamp
            self._t0_wall = self._clock()
        horizon = None if self.speed <= 0 else self.now()
        while self._pending is not None and len(out) < limit:
            t = self._pending._timestamp
            if horizon is not None and t > horizon:
                break
            out.append((self._pending, t))
            self._t_log = t
            self._read_next()
        if self._pending is None:
            self.finished = True
        return out

    def send_command(self, kind: str, target: tuple[int, int]) -> str:
        return f"{kind} ignored: replaying {os.path.basename(self.path)}, no link to the robot"

    def close(self) -> None:
        self._log.close()


def run_plain(source: MessageSource, view: VehicleView, out: IO[str], duration: float | None = None,
              period_s: float = 1.0, wall=time.monotonic, no_robot_s: float | None = None,
              on_wait: Callable[[str], None] | None = None,
              until: Callable[[VehicleView], bool] | None = None, where: str = "",
              where_note: str = "") -> int:
    """Feed `view` from `source`, printing a status line every `period_s` of source time and a last
    one at the end. Ends at the end of a replay, after `duration` wall seconds, once `until(view)`
    holds, or when no vehicle was heard within `no_robot_s` (no last line; `view.sysid` is None).
    `on_wait(line)` is told after 1 s without a vehicle what we wait for (`where`: " on URL",
    `where_note`: where the URL came from). Returns the number of lines printed."""
    start = wall()
    next_line: float | None = None
    lines = 0
    told = on_wait is None

    def tick(now: float) -> None:
        nonlocal next_line, lines
        if next_line is None:
            if view.t is not None:
                next_line = now + period_s
            return
        while now >= next_line:  # replay batches can span several seconds
            print(_stamp(view, next_line) + view.status_line(next_line), file=out, flush=True)
            lines += 1
            next_line += period_s

    while True:
        batch = source.poll()
        for msg, t in batch:
            tick(t)
            view.update(msg, t)
        tick(source.now())
        if source.finished or (duration is not None and wall() - start >= duration):
            break
        if until is not None and until(view):
            print(_stamp(view, source.now()) + view.status_line(source.now()), file=out, flush=True)
            lines += 1
            break
        if view.sysid is None:
            waited = wall() - start
            if not told and waited >= 1.0:
                assert on_wait is not None
                detail = "; ".join(x for x in (f"up to {no_robot_s:g} s" if no_robot_s is not None else "",
                                               where_note) if x)
                on_wait(f"waiting for a HEARTBEAT from a robot{where}" + (f" ({detail})" if detail else "") + " ...")
                told = True
            if no_robot_s is not None and waited >= no_robot_s:
                return lines
        if not batch:
            time.sleep(0.02)
    now = source.now()
    print(_stamp(view, now) + view.status_line(now), file=out, flush=True)
    return lines + 1


def _stamp(view: VehicleView, now: float) -> str:
    """The clock, named: `[robot 155.7s]` the robot's (sim time in HIL, not necessarily wall time) once
    it sends one, else `[recv 1.0s]`, the receive time since the first message."""
    robot = view.robot_clock(now)
    if robot is not None:
        return f"[robot {robot:8.1f}s] "
    rel = now - view.t0 if view.t0 is not None else 0.0
    return f"[recv  {rel:8.1f}s] "
