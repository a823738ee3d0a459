"""The live Foxglove bridge (`qnav monitor --foxglove`): the topics of
`ground_station.logs.topics`, published from the MAVLink link as it runs on
foxglove-sdk's WebSocket server (127.0.0.1 only), so Foxglove (desktop, or
its web app pointed at ws://127.0.0.1:PORT) shows the robot on its map.

A client may publish a goal on `/goal` (JSON `{"x": E, "y": N}` in map metres,
or a foxglove PoseInFrame / PoseStamped-like JSON with `pose.position`): it
is checked as `qnav goal` checks it (finite, inside the robot's local range)
and queued; the monitor's loop sends it (`take_goals`) as the same
SET_POSITION_TARGET_LOCAL_NED, so the link is only ever used from one
thread. The robot's answer comes back as telemetry (POSITION_TARGET_LOCAL_NED,
or a "goal refused: ..." line on /log); a refused publish is counted and
logged here.
"""

from __future__ import annotations

import json
import logging
import math
import queue
from typing import Any

from ground_station.logs.mcap_run import TopicSink
from ground_station.logs.topics import RunTopics

log = logging.getLogger("qnav.foxglove")
GOAL_TOPIC = "/goal"
DEFAULT_PORT = 8765  # Foxglove's own default


def parse_goal(data: bytes) -> tuple[float, float]:
    """A published goal -> (x east, y north) metres; ValueError with the reason."""
    from firmware_py.mavlink.mission import LOCAL_LIMIT_M

    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError):
        raise ValueError("goal is not JSON") from None
    if isinstance(doc, dict) and isinstance(doc.get("pose"), dict):
        doc = doc["pose"].get("position", doc["pose"])
    if not isinstance(doc, dict) or "x" not in doc or "y" not in doc:
        raise ValueError('goal needs "x" and "y" (metres, map frame)')
    try:
        x, y = float(doc["x"]), float(doc["y"])
    except (TypeError, ValueError):
        raise ValueError("goal x and y must be numbers") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError("goal x and y must be finite")
    if max(abs(x), abs(y)) > LOCAL_LIMIT_M:
        raise ValueError(f"goal ({x:g}, {y:g}) m is out of range (|x|, |y| <= {LOCAL_LIMIT_M:g} m)")
    return x, y


class FoxgloveBridge:
    """See the module docstring. `feed(msg, t)` for every received message."""

    def __init__(self, port: int = DEFAULT_PORT, grid_map=None) -> None:
        import foxglove

        self.topics = RunTopics(grid_map)
        self.context = foxglove.Context()
        self.sink = TopicSink(self.context)
        self.goals: queue.SimpleQueue[tuple[float, float]] = queue.SimpleQueue()
        self.refused_goals = 0
        self._client_topics: dict[tuple[int, int], str] = {}
        bridge = self

        class Listener(foxglove.ServerListener):
            def on_client_advertise(self, client: Any, channel: Any) -> None:
                bridge._client_topics[(client.id, channel.id)] = channel.topic

            def on_client_unadvertise(self, client: Any, client_channel_id: int) -> None:
                bridge._client_topics.pop((client.id, client_channel_id), None)

            def on_message_data(self, client: Any, client_channel_id: int, data: bytes) -> None:
                bridge._on_client_message(bridge._client_topics.get((client.id, client_channel_id), ""), data)

        self.server = foxglove.start_server(name="qnav", host="127.0.0.1", port=port, context=self.context,
                                            capabilities=[foxglove.Capability.ClientPublish],
                                            supported_encodings=["json"], server_listener=Listener())
        self.port = self.server.port
        self.sink.write(self.topics.map_grid(0))

    def _on_client_message(self, topic: str, data: bytes) -> None:
        if topic != GOAL_TOPIC:
            return
        try:
            self.goals.put(parse_goal(bytes(data)))
        except ValueError as exc:  # never raised into the server's thread
            self.refused_goals += 1
            log.warning("goal from Foxglove refused: %s", exc)

    def feed(self, msg, t_wall: float) -> None:
        self.sink.write(self.topics.mavlink(msg, t_wall))

    def take_goals(self) -> list[tuple[float, float]]:
        out = []
        while True:
            try:
                out.append(self.goals.get_nowait())
            except queue.Empty:
                return out

    def close(self) -> None:
        self.server.stop()


class BridgedSource:
    """A monitor `MessageSource` that also feeds a FoxgloveBridge and sends the
    goals published through it (on the monitor's own thread)."""

    def __init__(self, source, bridge: FoxgloveBridge) -> None:
        self.source = source
        self.bridge = bridge
        self.link = getattr(source, "link", None)

    @property
    def finished(self) -> bool:
        return bool(self.source.finished)

    def poll(self, limit: int = 2000) -> list[tuple[object, float]]:
        batch = self.source.poll(limit)
        for msg, t in batch:
            self.bridge.feed(msg, t)
        for x, y in self.bridge.take_goals():
            self.send_goal(x, y)
        return batch

    def send_goal(self, x: float, y: float) -> None:
        """What `qnav goal X Y` sends (the robot switches to Guided and echoes or refuses)."""
        conn = self.source.conn
        conn.mav.set_position_target_local_ned_send(0, conn.target_system or 1, conn.target_component or 1,
                                                    1, 0xFFF8, y, x, 0, 0, 0, 0, 0, 0, 0, 0, 0)  # MAV_FRAME_LOCAL_NED
        log.info("goal from Foxglove sent: x=%.2f y=%.2f m", x, y)

    def now(self) -> float:
        return float(self.source.now())

    def send_command(self, kind: str, target: tuple[int, int]) -> str:
        return str(self.source.send_command(kind, target))

    def close(self) -> None:
        try:
            self.bridge.close()
        finally:
            self.source.close()
