"""Opening the robot's CAN bus from one `--can` spec.

`open_bus(spec)` is the one place a `--can` value becomes a python-can bus:

    virtual:NAME                  python-can's in-process virtual bus
    remote:ws://127.0.0.1:PORT/   a python-can-remote hub (across processes; HIL runs
                                  only, so python-can-remote is the `qnav[hil]` extra)
    socketcan:CHANNEL             Linux SocketCAN (vcan0, can0)
    slcan:DEVICE                  serial-line CAN adapter (DEVICE[@BAUD])
    None or ""                    python-can's own configuration (CAN_INTERFACE,
                                  CAN_CHANNEL, ~/.canrc), resolved by python-can

The hub that separate processes of a HIL run meet on (`CanHub`) is the
ground station's (ground_station/canhub.py): the robot only connects to one,
through `hub_bus` below (python-can-remote's client, with buffered reads and
`send_all`). Stdlib and python-can (python-can-remote for `remote:`) only.

`send_all(bus, frames)` sends a tick's frames in order; on a hub in one
socket write, so a tick costs one system call each side instead of one per
frame (the hub sees the same frames in the same order).
"""

from __future__ import annotations

import functools
import importlib.util
import random
import select
import struct
from collections.abc import Sequence
from typing import Any

import can

SPEC_FORMS = ("virtual:NAME", "remote:ws://127.0.0.1:PORT/", "socketcan:CHANNEL", "slcan:DEVICE")


class CanSpecError(ValueError):
    """A `--can` value that cannot be turned into a bus; the text is one line."""


def parse_spec(spec: str | None) -> dict[str, Any]:
    """python-can keyword arguments for `spec` ({} means python-can's own config)."""
    if spec is None or spec.strip() == "":
        return {}
    interface, sep, channel = spec.partition(":")
    if not sep or not channel:
        raise CanSpecError(f"bad --can {spec!r}: expected one of {', '.join(SPEC_FORMS)}")
    if interface == "virtual":
        return {"interface": "virtual", "channel": channel}
    if interface == "remote":
        if not channel.startswith(("ws://", "wss://")):
            raise CanSpecError(f"bad --can {spec!r}: remote needs a ws:// URL, e.g. remote:ws://127.0.0.1:54701/")
        return {"interface": "remote", "channel": channel}
    if interface == "socketcan":
        return {"interface": "socketcan", "channel": channel}
    if interface == "slcan":
        return {"interface": "slcan", "channel": channel}
    raise CanSpecError(f"bad --can {spec!r}: unknown interface {interface!r} "
                       f"(expected virtual, remote, socketcan or slcan)")


def _installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def open_bus(spec: str | None, **kwargs: Any) -> can.BusABC:
    """Open the bus named by `spec` (see the module docstring); extra kwargs go to python-can."""
    config = parse_spec(spec)
    if config.get("interface") == "remote" and not _installed("can_remote"):
        raise CanSpecError(f"--can {spec}: the HIL hub transport needs python-can-remote: "
                           "pip install 'qnav[hil]'")
    config.update(kwargs)
    try:
        if config.get("interface") == "remote":
            return hub_bus(config.pop("channel"), **{k: v for k, v in config.items() if k != "interface"})
        return can.Bus(**config)
    except (can.CanError, OSError, ValueError, ImportError, TypeError) as exc:
        where = spec or "python-can default configuration"
        detail = " ".join(str(exc).split()) or type(exc).__name__
        raise CanSpecError(f"cannot open CAN bus {where!r}: {detail}") from None


def send_all(bus: can.BusABC, frames: Sequence[can.Message]) -> None:
    """Send `frames` in order: on a hub (`hub_bus`) in one write, else one `bus.send` each."""
    send_many = getattr(bus, "send_many", None)
    if send_many is not None:
        send_many(frames)
    else:
        for frame in frames:
            bus.send(frame)


# --- the python-can-remote client ---------------------------------------------------
# python-can-remote's WebSocket reads each frame with a select() and two recv() calls
# and writes each frame with its own sendall(); a lockstep tick is ~9 frames each way
# through the hub. The subclasses below read the socket in large chunks (every frame
# already received costs no system call) and write a tick's frames in one sendall().
# The bytes on the wire are python-can-remote's: binary messages, masked as a client's.

_BINARY_MSG = struct.Struct(">dIBB")  # can_remote.protocol: timestamp, id, dlc, flags
_WS_BINARY = 0x2
_FLAGS = (("is_extended_id", 0x1), ("is_remote_frame", 0x2), ("is_error_frame", 0x4),
          ("is_fd", 0x8), ("bitrate_switch", 0x10), ("error_state_indicator", 0x20))


def _binary_message(msg: can.Message) -> bytes:
    """A frame as python-can-remote's binary message (RemoteProtocolBase.send_msg)."""
    flags = 0
    for attr, bit in _FLAGS:
        if getattr(msg, attr):
            flags |= bit
    return b"\x01" + _BINARY_MSG.pack(msg.timestamp, msg.arbitration_id, msg.dlc, flags) + bytes(msg.data)


def _masked_frame(payload: bytes) -> bytes:
    """One masked binary WebSocket frame, as a client sends it (RFC 6455 5.2; WebSocket.send_frame)."""
    n = len(payload)
    if n <= 125:
        head = bytes((0x80 | _WS_BINARY, 0x80 | n))
    else:  # not a CAN frame's size (at most 15 + 64 bytes); kept for completeness
        head = bytes((0x80 | _WS_BINARY, 0x80 | 126)) + struct.pack(">H", n)
    mask = random.getrandbits(32).to_bytes(4, "big")
    key = int.from_bytes((mask * (n // 4 + 1))[:n], "big")
    return head + mask + (int.from_bytes(payload, "big") ^ key).to_bytes(n, "big")


def hub_bus(channel: str, **config: Any) -> can.BusABC:
    """python-can-remote's RemoteBus on `channel` (ws://HOST:PORT/) with buffered reads and `send_many`."""
    bus: can.BusABC = _hub_bus_class()(channel, **config)
    return bus


@functools.cache
def _hub_bus_class() -> type:
    # defined on first use: python-can-remote is an extra (qnav[hil]) and imports ssl
    from can_remote import client as remote_client  # type: ignore[import-untyped]
    from can_remote.websocket import WebSocket, WebsocketClosed  # type: ignore[import-untyped]

    class BufferedWebSocket(WebSocket):  # type: ignore[misc]
        """Reads the socket in chunks of up to 64 KiB: frames already received cost no system call."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            self._buf = bytearray()  # received, not read yet
            super().__init__(*args, **kwargs)

        def wait(self, timeout: float | None = None) -> bool:
            if self._buf:
                return True
            return len(select.select([self.socket], [], [], timeout)[0]) > 0

        def _read_exactly(self, n: int) -> bytearray:
            buf = self._buf
            while len(buf) < n:
                chunk = self.socket.recv(65536)
                if not chunk:
                    raise WebsocketClosed(1006, "Socket closed unexpectedly")
                buf += chunk
            out = buf[:n]
            del buf[:n]
            return out

    class HubBus(remote_client.RemoteBus):  # type: ignore[misc]
        def __init__(self, channel: str, ssl_context: Any = None, **config: Any) -> None:
            # RemoteBus.__init__, with the buffered WebSocket
            url = channel if "://" in channel else "ws://" + channel
            websocket = BufferedWebSocket(url, ["can.binary+json.v1", "can.json.v1"],
                                          ssl_context=ssl_context or remote_client.DEFAULT_SSL_CONTEXT)
            self.remote_protocol = remote_client.RemoteClientProtocol(config, websocket)
            self.socket = websocket.socket
            self.channel_info = self.remote_protocol.channel_info
            self.channel = channel
            can.BusABC.__init__(self, channel)

        def fileno(self) -> int:
            # a select() on the socket would miss frames already read into the buffer
            raise NotImplementedError("read with recv()")

        def send_many(self, frames: Sequence[can.Message]) -> None:
            """Send `frames` in order in one write (the bytes of one RemoteBus.send each)."""
            protocol = self.remote_protocol
            if not protocol._use_binary:  # a hub that speaks JSON only
                for frame in frames:
                    self.send(frame)
                return
            data = b"".join(_masked_frame(_binary_message(f)) for f in frames)
            ws = protocol._ws
            with ws._send_lock:
                if data and not ws.closed:
                    ws.socket.sendall(data)

    return HubBus
