"""The robot's own map for the monitor's dashboard and its Foxglove bridge.

`RobotMapSource` wraps a `LiveSource`: once a robot is heard it reads the map the robot drives on
over the monitor's own link, as `qnav mission upload` does
(`ground_station.mavlink.robot_map.robot_map`: its /maps/active.map with the targets sidecar, else
its active policy's map), and then asks every `CHECK_S` seconds for the CRC32 of /maps/active.map
and of /policies/active.qtab (MAVFTP CalcFileCRC32, one round trip each): when either changed (a
`qnav map upload`, a new policy activated) the map is read again. `grid_map` is the newest map (None
until read, or when the robot has none); `map_version` counts the changes, for the dashboard and the
bridge to follow.

The reads run on the monitor's thread, between two polls, so the link is used from one thread only;
the frames that arrive meanwhile (FTP requests consume the link) are caught by a pymavlink message
hook and handed out by the next `poll`, none lost. A robot that does not answer FTP (no storage,
another autopilot) is asked once: the line says so and names `--map`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

CHECK_S = 5.0  # wall seconds between two CRC checks of the robot's map and policy
CRC_WAIT_S = 3.0
MAV_TYPE_GCS = 6


class RobotMapSource:
    """See the module docstring. `say(line)`: one line for the operator (what map is shown, or why none)."""

    finished = False

    def __init__(self, source: Any, say: Callable[[str], None], target_system: int | None = None,
                 check_s: float = CHECK_S) -> None:
        self.source = source
        self.link = source.link
        self.conn = source.conn
        self.say = say
        self.check_s = check_s
        self.want_sysid = target_system
        self.grid_map: Any = None
        self.map_version = 0
        self._key: tuple[int | None, int | None] | None = None  # (map CRC, policy CRC) of the map read
        self._target: tuple[int, int] | None = None
        self._held: list[tuple[object, float]] = []
        self._next_check = 0.0
        self._gave_up = False

    def now(self) -> float:
        return float(self.source.now())

    def send_command(self, kind: str, target: tuple[int, int]) -> str:
        return str(self.source.send_command(kind, target))

    def close(self) -> None:
        self.source.close()

    def poll(self, limit: int = 2000) -> list[tuple[object, float]]:
        out, self._held = self._held, []
        out += self.source.poll(limit)
        if self._target is None:
            for msg, _t in out:
                get_type = getattr(msg, "get_type", None)
                if get_type is None or get_type() != "HEARTBEAT" or msg.type == MAV_TYPE_GCS:  # type: ignore[attr-defined]
                    continue
                src = msg.get_srcSystem()  # type: ignore[attr-defined]
                if self.want_sysid is None or src == self.want_sysid:
                    self._target = (src, msg.get_srcComponent())  # type: ignore[attr-defined]
                    break
        if self._target is not None and not self._gave_up and time.monotonic() >= self._next_check:
            self._check()
            self._next_check = time.monotonic() + self.check_s
        return out

    def _hold(self, _conn: Any, msg: Any) -> None:
        if msg.get_type() != "BAD_DATA":
            self._held.append((msg, self.source.now()))

    def _check(self) -> None:
        from ground_station.errors import CliError
        from ground_station.mavlink.ftp_upload import ftp_session
        from ground_station.mavlink.link import LinkError
        from ground_station.mavlink.robot_map import ACTIVE_MAP, ACTIVE_POLICY, robot_map

        link = self.link
        if link.target is None:
            assert self._target is not None
            link.target = self._target
            self.conn.target_system, self.conn.target_component = self._target
        self.conn.message_hooks.append(self._hold)
        try:
            session = ftp_session(link)
            key = (session.remote_crc(ACTIVE_MAP, wait_s=CRC_WAIT_S),
                   session.remote_crc(ACTIVE_POLICY, wait_s=CRC_WAIT_S))
            if key == self._key:
                return
            self._key = key
            gm = robot_map(link)
        except LinkError as exc:
            self._gave_up = True
            self.say(f"the robot's map cannot be read ({exc}): no map shown; give --map NAME|PATH")
            return
        except CliError as exc:  # e.g. it runs a policy not in its storage: asked again when a CRC changes
            self.say(f"{exc}")
            return
        finally:
            self.conn.message_hooks.remove(self._hold)
        self.grid_map = gm
        self.map_version += 1
        if gm is None:
            self.say("the robot has no map (no /maps/active.map, its policy carries none): no map shown")
        else:
            self.say(f"showing the robot's map {gm.name} ({gm.width}x{gm.height} cells of {gm.cell_size_m:g} m)")
