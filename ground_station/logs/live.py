"""The live Foxglove bridge (`qnav monitor --foxglove`): the topics of `ground_station.logs.topics`,
published from the MAVLink link as it runs on foxglove-sdk's WebSocket server (127.0.0.1 only),
so Foxglove (desktop, or its web app pointed at ws://127.0.0.1:PORT) shows the robot on its map.

`HandshakeGate` owns the public port and relays a connection, byte for byte, to the SDK's server on
a random loopback address only when its Origin is allowed (or absent) and it carries the token, if
one is set; it serves both subprotocol names, `foxglove.sdk.v1` and `foxglove.websocket.v1`. `/map`
is latched (sent again to a new subscriber and on `set_map`). Read-only unless `--foxglove-goals`:
then a `/goal` a client publishes is checked as `qnav goal` checks it and queued, and the monitor's
loop sends it (`take_goals`, one thread on the link) only while the robot's latest HEARTBEAT says
Guided. Who may connect, the subprotocols and the goal rules: docs/monitor.md, "A run in Foxglove,
PlotJuggler and Rerun".
"""

from __future__ import annotations

import contextlib
import hmac
import json
import logging
import math
import queue
import random
import socket
import threading
from collections.abc import Callable, Iterable
from typing import Any
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import foxglove
from foxglove import messages as fm

from ground_station.logs.mcap_run import TopicSink
from ground_station.logs.topics import Record, RunTopics

log = logging.getLogger("qnav.foxglove")
GOAL_TOPIC = "/goal"
DEFAULT_PORT = 8765  # Foxglove's own default
# Origins a browser client may come from without --foxglove-origin: Foxglove's web app
# (https://app.foxglove.dev, pointed at ws://127.0.0.1:PORT). Any other page is refused.
DEFAULT_ORIGINS = ("https://app.foxglove.dev",)
GUIDED = 15  # HEARTBEAT custom_mode of Guided (ArduPilot Rover numbering, firmware_py.vehicle.Mode)
GOAL_HEARTBEAT_AGE_S = 3.0  # a goal needs a HEARTBEAT saying Guided at most this old
HEAD_LIMIT = 16384  # bytes of an HTTP upgrade request (and of the SDK's 101 answer)
SDK_SUBPROTOCOL = "foxglove.sdk.v1"  # the only name foxglove-sdk 0.30's server accepts
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"  # the ws-protocol spec's name of the same protocol
HEAD_TIMEOUT_S = 5.0


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


def normalise_origin(origin: str) -> str:
    """An origin as browsers send it: scheme://host[:port], lower case, no trailing slash."""
    return origin.strip().rstrip("/").lower()


def offered_subprotocols(head: bytes) -> list[str]:
    """The subprotocols an upgrade request offers, in order."""
    out = []
    for line in head.decode("latin-1").split("\r\n")[1:]:
        name, sep, value = line.partition(":")
        if sep and name.strip().lower() == "sec-websocket-protocol":
            out += [v.strip() for v in value.split(",") if v.strip()]
    return out


def as_sdk_request(head: bytes) -> tuple[bytes, bool]:
    """(head to relay, legacy): a request offering `foxglove.websocket.v1` but not `foxglove.sdk.v1`
    offers the SDK `foxglove.sdk.v1` instead (legacy True); any other request unchanged."""
    offered = offered_subprotocols(head)
    if SDK_SUBPROTOCOL in offered or LEGACY_SUBPROTOCOL not in offered:
        return head, False
    lines = head.decode("latin-1").split("\r\n")
    kept = [lines[0]] + [ln for ln in lines[1:] if ln.partition(":")[0].strip().lower() != "sec-websocket-protocol"]
    return "\r\n".join([*kept, f"Sec-WebSocket-Protocol: {SDK_SUBPROTOCOL}"]).encode("latin-1"), True


def as_legacy_answer(head: bytes) -> bytes:
    """The SDK's answer to a legacy client: its `Sec-WebSocket-Protocol: foxglove.sdk.v1` says
    `foxglove.websocket.v1` (the subprotocol the client offered)."""
    lines = head.decode("latin-1").split("\r\n")
    out = [f"{ln.partition(':')[0]}: {LEGACY_SUBPROTOCOL}"
           if ln.partition(":")[0].strip().lower() == "sec-websocket-protocol"
           and ln.partition(":")[2].strip() == SDK_SUBPROTOCOL else ln for ln in lines]
    return "\r\n".join(out).encode("latin-1")


class HandshakeGate:
    """A TCP front for the SDK's WebSocket server (see the module docstring): `check(head)` says why
    a handshake is refused ("" = relay it). Listens on (host, port) at once (an error raises
    here); `close()` stops it and every relayed connection."""

    def __init__(self, upstream: tuple[str, int], host: str = "127.0.0.1", port: int = DEFAULT_PORT, *,
                 origins: Iterable[str] = DEFAULT_ORIGINS, token: str | None = None,
                 on_refuse: Callable[[str], None] | None = None) -> None:
        self.upstream = upstream
        self.origins = frozenset(normalise_origin(o) for o in origins)
        self.token = token or None
        self.on_refuse = on_refuse
        self._listener = socket.create_server((host, port))
        self.port = self._listener.getsockname()[1]
        self._socks: set[socket.socket] = set()
        self._lock = threading.Lock()
        self._closed = False
        threading.Thread(target=self._accept, name="foxglove-gate", daemon=True).start()

    def check(self, head: bytes) -> tuple[int, str, bytes]:
        """(HTTP status, reason, head to relay) of one upgrade request; status 0 = relay."""
        try:
            text = head.decode("latin-1")
            request_line, *lines = text.split("\r\n")
            method, target, _version = request_line.split(" ", 2)
        except ValueError:
            return 400, "not an HTTP request", b""
        headers: dict[str, list[str]] = {}
        for line in lines:
            if ":" in line:
                name, value = line.split(":", 1)
                headers.setdefault(name.strip().lower(), []).append(value.strip())
        origins = headers.get("origin", [])
        if len(origins) > 1:
            return 403, "more than one Origin header", b""
        if origins and normalise_origin(origins[0]) not in self.origins:
            return 403, f"Origin {origins[0]!r} not allowed (add it with --foxglove-origin)", b""
        parts = urlsplit(target)
        query = parse_qsl(parts.query, keep_blank_values=True)
        if self.token is not None:
            given = [v for k, v in query if k == "token"]
            given += [v[7:].strip() for v in headers.get("authorization", []) if v[:7].lower() == "bearer "]
            if not any(hmac.compare_digest(g.encode(), self.token.encode()) for g in given):
                return 401, "no valid token (?token=... in the URL or Authorization: Bearer ...)", b""
        # the token goes no further than here
        relayed_target = urlunsplit(("", "", parts.path or "/", urlencode([(k, v) for k, v in query if k != "token"]), ""))
        if method != "GET":
            return 400, f"{method} is not a WebSocket upgrade", b""
        return 0, "", (" ".join((method, relayed_target, _version)) + "\r\n" + "\r\n".join(lines)).encode("latin-1")

    def _accept(self) -> None:
        while True:
            try:
                client, _addr = self._listener.accept()
            except OSError:  # closed
                return
            threading.Thread(target=self._serve, args=(client,), name="foxglove-gate-conn", daemon=True).start()

    def _track(self, sock: socket.socket) -> bool:
        with self._lock:
            if self._closed:
                return False
            self._socks.add(sock)
            return True

    def _forget(self, *socks: socket.socket) -> None:
        with self._lock:
            for sock in socks:
                self._socks.discard(sock)
        for sock in socks:
            with contextlib.suppress(OSError):
                sock.close()

    def _serve(self, client: socket.socket) -> None:
        if not self._track(client):
            client.close()
            return
        upstream = None
        try:
            client.settimeout(HEAD_TIMEOUT_S)
            read = _read_head(client)
            if read is None:
                return
            head, rest = read
            status, why, relay_head = self.check(head)
            if status:
                phrase = {400: "Bad Request", 401: "Unauthorized", 403: "Forbidden"}.get(status, "Forbidden")
                body = f"qnav monitor: {why}\n".encode()
                client.sendall(f"HTTP/1.1 {status} {phrase}\r\nContent-Type: text/plain\r\n"
                               f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode() + body)
                if self.on_refuse is not None:
                    self.on_refuse(why)
                return
            relay_head, legacy = as_sdk_request(relay_head)
            upstream = socket.create_connection(self.upstream, timeout=HEAD_TIMEOUT_S)
            if not self._track(upstream):
                return
            upstream.sendall(relay_head + b"\r\n\r\n" + rest)
            if legacy:  # the SDK's 101 answer, its subprotocol put back to the one offered
                answer = _read_head(upstream)
                if answer is None:
                    return
                answer_head, after = answer
                client.sendall(as_legacy_answer(answer_head) + b"\r\n\r\n" + after)
            client.settimeout(None)
            upstream.settimeout(None)
            back = threading.Thread(target=self._pump, args=(upstream, client), name="foxglove-gate-down",
                                    daemon=True)
            back.start()
            self._pump(client, upstream)
            back.join()
        except OSError:
            pass
        finally:
            self._forget(client, *((upstream,) if upstream is not None else ()))

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        try:
            while True:
                data = src.recv(65536)
                if not data:
                    break
                dst.sendall(data)
        except OSError:
            pass
        finally:  # one side ended: end both directions
            for sock in (src, dst):
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            socks = list(self._socks)
        with contextlib.suppress(OSError):
            self._listener.close()
        for sock in socks:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)


def _read_head(sock: socket.socket) -> tuple[bytes, bytes] | None:
    """An HTTP head from `sock` and the bytes after it; None if the peer closed first or it is too long."""
    buf = b""
    while b"\r\n\r\n" not in buf:
        chunk = sock.recv(4096)
        if not chunk or len(buf) + len(chunk) > HEAD_LIMIT:
            return None
        buf += chunk
    head, rest = buf.split(b"\r\n\r\n", 1)
    return head, rest


def _hidden_loopback_server(start: Callable[[str], Any]) -> tuple[Any, str]:
    """`start(host)` on a random 127.x.y.z address (Linux routes all of 127/8 to the loopback), so
    that only the gate knows where the SDK's server is; where the system has 127.0.0.1 only,
    there (with a warning: a page that finds its port passes no gate)."""
    rng = random.SystemRandom()
    for _ in range(3):
        host = f"127.{rng.randrange(1, 255)}.{rng.randrange(0, 256)}.{rng.randrange(1, 255)}"
        try:
            return start(host), host
        except Exception as exc:  # noqa: BLE001 - foxglove raises its own error type for a bind failure
            last = exc
    log.warning("Foxglove bridge: cannot bind a random loopback address (%s); the server behind the "
                "origin check listens on 127.0.0.1", last)
    return start("127.0.0.1"), "127.0.0.1"


class FoxgloveBridge:
    """See the module docstring. `feed(msg, t)` for every received message.
    `goals`: clients may publish /goal (else the server is read-only);
    `origins`, `token`: what `HandshakeGate` lets in."""

    def __init__(self, port: int = DEFAULT_PORT, grid_map=None, *, goals: bool = False,
                 origins: Iterable[str] = DEFAULT_ORIGINS, token: str | None = None) -> None:
        self.topics = RunTopics(grid_map)
        self.context = foxglove.Context()
        self.sink = TopicSink(self.context)
        self.goals_enabled = goals
        self.goals: queue.SimpleQueue[tuple[float, float]] = queue.SimpleQueue()
        self._client_topics: dict[tuple[int, int], str] = {}
        self._said: queue.SimpleQueue[tuple[str, bool]] = queue.SimpleQueue()  # lines for /log, from any thread
        self._map_wanted = threading.Event()  # a client subscribed to /map: send it again (latched)
        self._log_ns = 0
        bridge = self

        class Listener(foxglove.ServerListener):
            def on_subscribe(self, client: Any, channel: Any) -> None:
                if channel.topic == "/map":  # the monitor's thread sends it (never from the server's)
                    bridge._map_wanted.set()

            def on_client_advertise(self, client: Any, channel: Any) -> None:
                bridge._client_topics[(client.id, channel.id)] = channel.topic

            def on_client_unadvertise(self, client: Any, client_channel_id: int) -> None:
                bridge._client_topics.pop((client.id, client_channel_id), None)

            def on_message_data(self, client: Any, client_channel_id: int, data: bytes) -> None:
                bridge._on_client_message(bridge._client_topics.get((client.id, client_channel_id), ""), data)

        def start(host: str) -> Any:
            return foxglove.start_server(name="qnav", host=host, port=0, context=self.context,
                                         capabilities=[foxglove.Capability.ClientPublish] if goals else [],
                                         supported_encodings=["json"], server_listener=Listener())

        self.server, self.server_host = _hidden_loopback_server(start)
        try:
            self.gate = HandshakeGate((self.server_host, self.server.port), port=port, origins=origins,
                                      token=token, on_refuse=self._on_refused)
        except BaseException:
            self.server.stop()
            raise
        self.port = self.gate.port
        self._write_map(0)

    def _write_map(self, ns: int) -> None:
        self.sink.write(self.topics.map_grid(ns, again=True))

    def set_map(self, grid_map, t_wall: float) -> None:
        """A new map (the robot's, read or changed): sent now to every subscriber of /map."""
        self.topics.grid_map = grid_map
        self._map_wanted.clear()
        self._write_map(self.topics.robot_ns(t_wall) or 0)

    def flush_map(self, t_wall: float) -> None:
        """The map again if a client subscribed to /map since the last call (monitor's thread)."""
        if self._map_wanted.is_set():
            self._map_wanted.clear()
            self._write_map(self.topics.robot_ns(t_wall) or 0)

    def _on_refused(self, why: str) -> None:
        self.say(f"refused a WebSocket client: {why}", warning=True)

    def say(self, text: str, warning: bool = False) -> None:
        """A line from the bridge: stderr (logging) now, `/log` on the monitor's next poll."""
        (log.warning if warning else log.info)("Foxglove bridge: %s", text)
        self._said.put((text, warning))

    def flush_log(self, t_wall: float) -> None:
        """The lines `say` queued, onto /log (called from the monitor's thread)."""
        while True:
            try:
                text, warning = self._said.get_nowait()
            except queue.Empty:
                return
            ns = max(self.topics.robot_ns(t_wall) or 0, self._log_ns)
            self._log_ns = ns
            self.sink.write([Record("/log", fm.Log(timestamp=fm.Timestamp(ns // 1_000_000_000, ns % 1_000_000_000),
                                                   level=fm.LogLevel.Warning if warning else fm.LogLevel.Info,
                                                   message=text, name="qnav monitor"), ns)])

    def _on_client_message(self, topic: str, data: bytes) -> None:
        if topic != GOAL_TOPIC:
            return
        if not self.goals_enabled:  # the server offers no publishing then; never act on it regardless
            self.say("goal from Foxglove refused: the bridge is read-only (qnav monitor --foxglove-goals)",
                     warning=True)
            return
        try:
            self.goals.put(parse_goal(bytes(data)))
        except ValueError as exc:  # never raised into the server's thread
            self.say(f"goal from Foxglove refused: {exc}", warning=True)

    def guided_now(self, t_wall: float) -> tuple[bool, str]:
        """Whether the followed robot's latest HEARTBEAT (at most GOAL_HEARTBEAT_AGE_S old) says Guided."""
        view = self.topics.view
        age = view.heartbeat_age(t_wall)
        if view.mode is None or age is None:
            return False, "no HEARTBEAT from the robot yet"
        if age > GOAL_HEARTBEAT_AGE_S:
            return False, f"the robot's last HEARTBEAT is {age:.1f} s old"
        if view.mode != GUIDED:
            return False, f"the robot is in {view.mode_name}, not Guided (set mode Guided first)"
        return True, ""

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
        try:
            self.gate.close()
        finally:
            self.server.stop()


class BridgedSource:
    """A monitor `MessageSource` that also feeds a FoxgloveBridge and sends the
    goals published through it (on the monitor's own thread)."""

    def __init__(self, source, bridge: FoxgloveBridge) -> None:
        self.source = source
        self.bridge = bridge
        self.link = getattr(source, "link", None)
        self._map_version = getattr(source, "map_version", 0)

    @property
    def grid_map(self):
        """The robot's map, when the wrapped source reads it (`RobotMapSource`)."""
        return getattr(self.source, "grid_map", None)

    @property
    def map_version(self) -> int:
        return int(getattr(self.source, "map_version", 0))

    @property
    def finished(self) -> bool:
        return bool(self.source.finished)

    def poll(self, limit: int = 2000) -> list[tuple[object, float]]:
        batch = self.source.poll(limit)
        for msg, t in batch:
            self.bridge.feed(msg, t)
        now = self.now()
        if self.map_version != self._map_version:  # the robot's map, read or changed
            self._map_version = self.map_version
            self.bridge.set_map(self.grid_map, now)
        self.bridge.flush_map(now)
        for x, y in self.bridge.take_goals():
            ok, why = self.bridge.guided_now(now)
            if ok:
                self.send_goal(x, y)
            else:
                self.bridge.say(f"goal from Foxglove x={x:.2f} y={y:.2f} m dropped: {why}", warning=True)
        self.bridge.flush_log(now)
        return batch

    def send_goal(self, x: float, y: float) -> None:
        """What `qnav goal X Y` sends once the robot is in Guided (the robot echoes or refuses it)."""
        conn = self.source.conn
        conn.mav.set_position_target_local_ned_send(0, conn.target_system or 1, conn.target_component or 1,
                                                    1, 0xFFF8, y, x, 0, 0, 0, 0, 0, 0, 0, 0, 0)  # MAV_FRAME_LOCAL_NED
        self.bridge.say(f"goal from Foxglove sent: x={x:.2f} y={y:.2f} m")

    def now(self) -> float:
        return float(self.source.now())

    def send_command(self, kind: str, target: tuple[int, int]) -> str:
        return str(self.source.send_command(kind, target))

    def close(self) -> None:
        try:
            self.bridge.close()
        finally:
            self.source.close()
