"""What a run looks like to Foxglove, PlotJuggler and Rerun: MAVLink, CAN and
the sim's ground truth turned into topics (pure: records in, records out).

`RunTopics` takes the run's inputs in any order per source and returns `Record`s (topic, message,
log time); `ground_station.logs.mcap_run` writes them to one MCAP file, `ground_station.logs.live`
publishes them on a foxglove-sdk WebSocket server. The same topics either way:

| topic | message | from |
| --- | --- | --- |
| `/pose` | foxglove.PoseInFrame (frame `map`) | LOCAL_POSITION_NED + ATTITUDE: the robot's believed pose |
| `/tf` | foxglove.FrameTransform `map` -> `base_link` | the same |
| `/odom` | foxglove.PoseInFrame | ODOMETRY (raw dead reckoning), when the robot sends it |
| `/location` | foxglove.LocationFix | GLOBAL_POSITION_INT (the map panel) |
| `/scan` | foxglove.LaserScan (frame `base_link`) | OBSTACLE_DISTANCE (the range sectors) |
| `/map` | foxglove.Grid (frame `map`) | the occupancy map: once in a file; live, again for every new subscriber and when the robot's map changes |
| `/mission` | foxglove.SceneUpdate | MISSION_ITEM_INT (targets as spheres) |
| `/log` | foxglove.Log | STATUSTEXT (whole texts) |
| `/robot_log` | foxglove.Log | the robot's own log (robot.log of a run), at its `t=... us` control-clock times |
| `/vehicle` | JSON | mode, armed, controller state, action, state index, the policy's Q row, load, tick overruns |
| `/mavlink/<TYPE>` | JSON (one per message type) | every MAVLink message, as pymavlink decodes it |
| `/can/<Message>` | JSON | every CAN frame the DBC knows, signals as fields |
| `/can/raw` | JSON | every CAN frame: id, data, dlc |
| `/truth` | foxglove.PoseInFrame (frame `map`) | the sim's ground truth (trajectory.csv) |
| `/tf_truth` | foxglove.FrameTransform `map` -> `truth` | the same |

Times: the robot's clock (its `time_boot_ms`; sim time in HIL), as `VehicleView` follows it; a
message without its own time gets the newest robot time plus the receive time since. CAN frames take
the sim time of the newest SimTick plus the bus time since; the truth its own sim time. The receive
(wall) time is kept as the `wall_time` field of the JSON topics. Log times are kept monotonic per
topic (a late frame gets its topic's last time).

Foxglove's well-known schemas go as protobuf (foxglove-sdk's typed channels: what Foxglove,
PlotJuggler and Rerun decode without help); the rest as JSON with a JSON schema derived from the
first message, so every field is plottable by name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from foxglove import messages as fm

from ground_station.monitor.model import VehicleView, obstacle_increment_deg

MAP_FRAME, ROBOT_FRAME, TRUTH_FRAME = "map", "base_link", "truth"


@dataclass
class Record:
    topic: str
    message: Any  # a foxglove.messages instance, or a JSON-ready dict
    log_time_ns: int


def _stamp(ns: int):
    return fm.Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _xyz_q(x: float, y: float, yaw: float):
    return (fm.Vector3(x=x, y=y, z=0.0),
            fm.Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))


def _pose(x: float, y: float, yaw: float):
    position, orientation = _xyz_q(x, y, yaw)
    return fm.Pose(position=position, orientation=orientation)


def _transform(ns: int, child: str, x: float, y: float, yaw: float):
    translation, rotation = _xyz_q(x, y, yaw)
    return fm.FrameTransform(timestamp=_stamp(ns), parent_frame_id=MAP_FRAME, child_frame_id=child,
                             translation=translation, rotation=rotation)


def json_schema(sample: dict[str, Any]) -> dict[str, Any]:
    """A JSON schema for dicts shaped like `sample` (numbers, strings, lists, booleans)."""
    def kind(v: Any) -> dict[str, Any]:
        if isinstance(v, bool):
            return {"type": "boolean"}
        if isinstance(v, (int, float)):
            return {"type": "number"}
        if isinstance(v, (list, tuple)):
            return {"type": "array", "items": kind(v[0]) if v else {}}
        if isinstance(v, dict):
            return json_schema(v)
        return {"type": "string"}
    return {"type": "object", "properties": {k: kind(v) for k, v in sample.items()}}


def _plain(v: Any) -> Any:
    if isinstance(v, (bytes, bytearray)):
        return v.hex()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


class RunTopics:
    """See the module docstring. One instance per run (it follows the robot's clock)."""

    def __init__(self, grid_map=None) -> None:
        self.view = VehicleView()
        self.grid_map = grid_map  # ground_station.maps.GridMap: its cells become /map
        self._last_ns: dict[str, int] = {}
        self._sim_tick: tuple[float, int] | None = None  # (bus time s, sim time us) of the newest SimTick
        self._map_sent = False
        self._logged = 0  # view.log_total already turned into /log records

    # --- helpers ------------------------------------------------------------------
    def _rec(self, topic: str, message: Any, ns: int) -> Record:
        ns = max(int(ns), self._last_ns.get(topic, 0))
        self._last_ns[topic] = ns
        return Record(topic, message, ns)

    def robot_ns(self, t_wall: float) -> int | None:
        """The robot time (ns) of a message received at `t_wall` (None before any timed message)."""
        rel = self.view.robot_clock(t_wall)
        if rel is None or self.view.robot_s0 is None:
            return None
        return int(round((self.view.robot_s0 + rel) * 1e9))

    def map_grid(self, ns: int = 0, again: bool = False) -> list[Record]:
        """The occupancy map as a foxglove Grid (row 0 of the data is the map's south edge): once, or
        `again` (the live bridge latches it: re-sent for a new subscriber and when the map changes)."""
        gm = self.grid_map
        if gm is None or (self._map_sent and not again):
            return []
        self._map_sent = True
        h, w = gm.occ.shape
        rows = [bytes(100 if gm.occ[h - 1 - r, c] else 0 for c in range(w)) for r in range(h)]
        grid = fm.Grid(timestamp=_stamp(ns), frame_id=MAP_FRAME, pose=_pose(0.0, 0.0, 0.0), column_count=w,
                       cell_size=fm.Vector2(x=gm.cell_size_m, y=gm.cell_size_m), row_stride=w, cell_stride=1,
                       fields=[fm.PackedElementField(name="occupancy", offset=0,
                                                     type=fm.PackedElementFieldNumericType.Uint8)],
                       data=b"".join(rows))
        return [self._rec("/map", grid, ns)]

    # --- MAVLink ------------------------------------------------------------------
    def mavlink(self, msg, t_wall: float) -> list[Record]:
        """Records for one MAVLink message of the session (either direction): its
        `/mavlink/<TYPE>` record always; the derived topics for our robot's."""
        ours = self.view.update(msg, t_wall)
        ns = self.robot_ns(t_wall) or 0
        mtype = msg.get_type()
        d = {k: _plain(v) for k, v in msg.to_dict().items() if k != "mavpackettype"}
        d.update(src_system=msg.get_srcSystem(), src_component=msg.get_srcComponent(), wall_time=t_wall)
        out = self.map_grid(ns)
        out.append(self._rec(f"/mavlink/{mtype}", d, ns))
        if not ours:
            return out
        handler = getattr(self, "_on_" + mtype.lower(), None)
        if handler is not None:
            out += handler(msg, ns, t_wall)
        return out + self._new_log_lines(ns)

    def _new_log_lines(self, ns: int) -> list[Record]:
        """STATUSTEXTs the view completed (a chunked text ends when its last chunk, or
        another message, arrives)."""
        v = self.view
        new = min(v.log_total - self._logged, len(v.log))
        self._logged = v.log_total
        if new <= 0:
            return []
        out = []
        for line in list(v.log)[-new:]:
            level = (fm.LogLevel.Error if line.severity <= 3 else
                     fm.LogLevel.Warning if line.severity == 4 else fm.LogLevel.Info)
            out.append(self._rec("/log", fm.Log(timestamp=_stamp(ns), level=level, message=line.text,
                                                 name="robot"), ns))
        return out

    def _pose_records(self, ns: int) -> list[Record]:
        v = self.view
        if v.pose is None:
            return []
        x, y, yaw = v.pose
        pose = fm.PoseInFrame(timestamp=_stamp(ns), frame_id=MAP_FRAME, pose=_pose(x, y, yaw))
        return [self._rec("/pose", pose, ns), self._rec("/tf", _transform(ns, ROBOT_FRAME, x, y, yaw), ns)]

    def _on_local_position_ned(self, msg, ns: int, t_wall: float) -> list[Record]:
        return self._pose_records(ns)

    def _on_odometry(self, msg, ns: int, t_wall: float) -> list[Record]:
        q = msg.q  # NED (w, x, y, z); yaw clockwise from north -> ours counter-clockwise from east
        yaw_ned = math.atan2(2 * (q[0] * q[3] + q[1] * q[2]), 1 - 2 * (q[2] ** 2 + q[3] ** 2))
        pose = _pose(float(msg.y), float(msg.x), math.pi / 2 - yaw_ned)
        return [self._rec("/odom", fm.PoseInFrame(timestamp=_stamp(ns), frame_id=MAP_FRAME, pose=pose), ns)]

    def _on_global_position_int(self, msg, ns: int, t_wall: float) -> list[Record]:
        fix = fm.LocationFix(timestamp=_stamp(ns), frame_id=MAP_FRAME, latitude=msg.lat / 1e7,
                             longitude=msg.lon / 1e7, altitude=msg.alt / 1000)
        return [self._rec("/location", fix, ns)]

    def _on_obstacle_distance(self, msg, ns: int, t_wall: float) -> list[Record]:
        inc_deg = obstacle_increment_deg(msg)
        if inc_deg <= 0:
            return []
        n = min(len(msg.distances), max(1, round(360 / inc_deg)))
        # MAV_FRAME_BODY_FRD bins clockwise from the nose (65535: no sensor there, > max: nothing in
        # range); a LaserScan runs counter-clockwise from +x: bin 0, then the bins from the left round
        rng = [math.nan if d == 65535 else math.inf if d > msg.max_distance else d / 100.0
               for d in msg.distances[:n]]
        ranges = [rng[0], *reversed(rng[1:])]
        inc = math.radians(inc_deg)
        start = -math.radians(getattr(msg, "angle_offset", 0.0) or 0.0)
        scan = fm.LaserScan(timestamp=_stamp(ns), frame_id=ROBOT_FRAME, pose=_pose(0.0, 0.0, 0.0),
                            start_angle=start, end_angle=start + inc * (n - 1), ranges=ranges)
        return [self._rec("/scan", scan, ns)]

    def _on_heartbeat(self, msg, ns: int, t_wall: float) -> list[Record]:
        return self._vehicle(ns, t_wall)

    def _on_named_value_int(self, msg, ns: int, t_wall: float) -> list[Record]:
        # published once a group's Q row is whole (Q_N), never half-updated between its values
        return self._vehicle(ns, t_wall) if self.view.q_row_ready else []

    def _vehicle(self, ns: int, t_wall: float) -> list[Record]:
        v = self.view
        d = {"mode": int(v.mode or 0), "armed": bool(v.armed), "system_status": int(v.system_status or 0),
             "ctrl_state": int(v.ctrl_state if v.ctrl_state is not None else -1),
             "action": int(v.action if v.action is not None else -1),
             "state_index": int(v.state_index if v.state_index is not None else -1), "load_pct": float(v.load_pct or 0.0),
             "tick_overruns": int(v.link.tick_overruns or 0),
             "q_row": [int(v.q_row[k]) for k in sorted(v.q_row)], "wall_time": t_wall}
        return [self._rec("/vehicle", d, ns)]

    def _on_mission_item_int(self, msg, ns: int, t_wall: float) -> list[Record]:
        items = sorted(self.view.mission.items.items())
        spheres = [fm.SpherePrimitive(pose=_pose(x, y, 0.0), size=fm.Vector3(x=0.2, y=0.2, z=0.2),
                                      color=fm.Color(r=0.1, g=0.6, b=1.0, a=0.8)) for _seq, (x, y) in items]
        texts = [fm.TextPrimitive(pose=_pose(x, y + 0.25, 0.0), billboard=True, font_size=14.0,
                                  scale_invariant=True, color=fm.Color(r=1, g=1, b=1, a=1), text=str(seq))
                 for seq, (x, y) in items]
        ent = fm.SceneEntity(timestamp=_stamp(ns), frame_id=MAP_FRAME, id="mission", spheres=spheres, texts=texts)
        return [self._rec("/mission", fm.SceneUpdate(entities=[ent]), ns)]

    # --- CAN ----------------------------------------------------------------------
    def can_frame(self, arbitration_id: int, data: bytes, t_bus: float) -> list[Record]:
        """Records for one CAN frame seen at bus time `t_bus` (seconds)."""
        from firmware_py import can_protocol as cp

        name, sig = None, None
        # only an id our DBC has is decoded (most frames of a run are not: DroneCAN's, ODrive's)
        if cp.frame_name(arbitration_id) is not None:
            try:
                import can

                name, sig = cp.decode(can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False))
            except Exception:  # noqa: BLE001 - a frame our DBC refuses is still logged raw
                name = None
        if name == "SimTick" and sig is not None:
            self._sim_tick = (t_bus, int(sig["Tick_SimTimeUs"]))
        if self._sim_tick is None:
            ns = 0
        else:
            ns = int(self._sim_tick[1] * 1000 + max(0.0, t_bus - self._sim_tick[0]) * 1e9)
        out = [self._rec("/can/raw", {"id": arbitration_id, "dlc": len(data), "data": bytes(data).hex(),
                                      "name": name or "", "wall_time": t_bus}, ns)]
        if name is not None and sig is not None:
            out.append(self._rec(f"/can/{name}", {**{k: _plain(v) for k, v in sig.items()}, "wall_time": t_bus}, ns))
        return out

    # --- the robot's own log ----------------------------------------------------------------
    def robot_log_line(self, line: str) -> list[Record]:
        """One line of qnav-robot's log ("qnav-robot LEVEL message"); its time is
        the control clock's `t=... us` when the line carries one, else the last."""
        import re

        line = line.rstrip("\n")
        if not line.strip():
            return []
        m = re.match(r"^\S+ (DEBUG|INFO|WARNING|ERROR|CRITICAL) (.*)$", line)
        level_name, text = (m.group(1), m.group(2)) if m else ("INFO", line)
        t = re.search(r"\bt=(\d+) us\b", text)
        ns = int(t.group(1)) * 1000 if t else self._last_ns.get("/robot_log", 0)
        level = {"DEBUG": fm.LogLevel.Debug, "INFO": fm.LogLevel.Info, "WARNING": fm.LogLevel.Warning,
                 "ERROR": fm.LogLevel.Error, "CRITICAL": fm.LogLevel.Fatal}[level_name]
        return [self._rec("/robot_log", fm.Log(timestamp=_stamp(ns), level=level, message=text,
                                               name="qnav-robot"), ns)]

    # --- sim ground truth -------------------------------------------------------------
    def truth(self, t_s: float, x_m: float, y_m: float, heading_rad: float) -> list[Record]:
        ns = int(round(t_s * 1e9))
        pose = fm.PoseInFrame(timestamp=_stamp(ns), frame_id=MAP_FRAME, pose=_pose(x_m, y_m, heading_rad))
        return [self._rec("/truth", pose, ns),
                self._rec("/tf_truth", _transform(ns, TRUTH_FRAME, x_m, y_m, heading_rad), ns)]
