"""The robot as a DroneCAN node: a pure engine on the `dronecan` library's DSDL and framing.

The `dronecan` library (the optional extra `qnav[dronecan]`) serialises DSDL types and decodes a
transfer from its frames. Its `Node` owns a driver and a thread; here the robot's node owns the
bus and the tick must send its wheel command in order with its other frames, so this engine does
no I/O: `take(msg, now)` reassembles a received 29-bit frame into a transfer (and notes a
GetNodeInfo request addressed to us), `broadcast(payload)` returns the frames of a message,
`periodic(now)` the NodeStatus due at 1 Hz, and `outgoing(now)` the answers due; the backends
(drives/dronecan.py, sensors) and the node's shell move the frames, the wheel command first.

What another node can make it hold or do is bounded:

* reassembly (`Reassembler`, no dronecan import): one transfer in progress per (data type, kind,
  source, destination) as libcanard keeps them, at most MAX_TRANSFERS at once; a transfer must end
  within TRANSFER_TIMEOUT_S (libcanard's 2 s) of its first frame on the robot's clock (the `now`
  the caller passes: sim time in HIL), and may not grow past its data type's largest encoding (the
  DSDL's max bit length + the 2-byte CRC); a type id no DSDL here defines is dropped at its first
  frame, before anything is buffered; a frame with the wrong transfer id or toggle bit is ignored.
* answers: GetNodeInfo is answered at most ANSWERS_PER_TICK a call of `outgoing` and
  ANSWERS_PER_S a second, one pending answer per requesting node, at most MAX_PENDING nodes.
* node-id collisions: a frame with our own node id as its source that we did not send (not one of
  our last frames echoed) is another node using our id; `collision(now)` says so, in words fit for
  a STATUSTEXT, until COLLISION_HOLD_S after the last such frame.

Standard ids only ever come from qnav's own frames and ODrives; every DroneCAN frame is extended.
"""

from __future__ import annotations

import functools
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can

try:
    import dronecan
    from dronecan import transport
except ImportError as exc:  # pragma: no cover - exercised by a robot without the extra
    raise ImportError("the dronecan backends need the dronecan library: pip install 'qnav[dronecan]'") from exc

NODE_STATUS_PERIOD_S = 1.0
PRIORITY_HIGH = 8  # commands (DroneCAN's "high" band; ArduPilot sends ESC commands at high priority)
PRIORITY_DEFAULT = 16
PRIORITY_LOW = 24

TRANSFER_TIMEOUT_S = 2.0  # libcanard's CANARD_DEFAULT_TRANSFER_ID_TIMEOUT_USEC (2 s), from the first frame
MAX_TRANSFERS = 32  # multi-frame transfers in progress at once (one per sender, type and kind)
ANSWERS_PER_TICK = 1  # GetNodeInfo answers a tick (9 frames of ours: ~1.2 ms of a 1 Mbit/s bus)
ANSWERS_PER_S = 10.0
MAX_PENDING = 16  # requesting nodes waiting for an answer; more are dropped (they ask again)
COLLISION_HOLD_S = 3.0  # a collision is "seen" this long after the last frame from our id (3 NodeStatus)
ECHO_FRAMES = 64  # our last frames, told apart from another node's with our id (a bus that echoes)

FRAME_PAYLOAD = 7  # data bytes a classic CAN frame carries besides the tail byte
CRC_BYTES = 2  # a multi-frame transfer's payload starts with its CRC


@dataclass(frozen=True)
class FrameHeader:
    """A DroneCAN (UAVCAN v0) 29-bit id and tail byte, decoded."""

    priority: int
    data_type_id: int
    service: bool
    request: bool  # services only
    source: int  # 0: anonymous
    dest: int  # services only (0 for messages)
    start: bool
    end: bool
    toggle: bool
    transfer_id: int

    @staticmethod
    def parse(can_id: int, data: bytes) -> FrameHeader:
        tail = data[-1]
        service = bool(can_id & 0x80)
        source = can_id & 0x7F
        if service:
            dtid, request, dest = (can_id >> 16) & 0xFF, bool(can_id & 0x8000), (can_id >> 8) & 0x7F
        else:
            dtid, request, dest = (can_id >> 8) & 0xFFFF, False, 0
            if source == 0:
                dtid &= 0x3  # an anonymous message: the upper bits carry a discriminator
        return FrameHeader((can_id >> 24) & 0x1F, dtid, service, request, source, dest, bool(tail & 0x80),
                           bool(tail & 0x40), bool(tail & 0x20), tail & 0x1F)

    @property
    def key(self) -> tuple[int, bool, bool, int, int]:
        """What libcanard keeps one transfer in progress for (the priority is not part of it)."""
        return self.data_type_id, self.service, self.request, self.source, self.dest


@dataclass
class _Partial:
    can_id: int
    transfer_id: int
    started: float
    max_frames: int
    frames: list[bytes] = field(default_factory=list)
    next_toggle: bool = True  # the frame after the first has the toggle bit set


class Reassembler:
    """Frames in, complete transfers (their id and frames' data) out, with bounded memory and time.

    `max_bytes(data_type_id, service, request)` is the largest payload of that type in bytes, None
    for a type id nobody here knows. Counters: `dropped` (unknown type, too long, no room, anonymous
    multi-frame), `timed_out`, `ignored` (continuations of nothing, wrong transfer id or toggle)."""

    def __init__(self, max_bytes: Callable[[int, bool, bool], int | None], *,
                 timeout_s: float = TRANSFER_TIMEOUT_S, max_transfers: int = MAX_TRANSFERS) -> None:
        self.max_bytes = max_bytes
        self.timeout_s = timeout_s
        self.max_transfers = max_transfers
        self._rx: dict[tuple[int, bool, bool, int, int], _Partial] = {}
        self._next_sweep = -float("inf")
        self.dropped = 0
        self.timed_out = 0
        self.ignored = 0

    def push(self, can_id: int, data: bytes, now: float, head: FrameHeader | None = None) -> list[bytes] | None:
        """The frames' data of a transfer once its last frame is in (one frame: a single-frame transfer)."""
        h = head or FrameHeader.parse(can_id, data)
        self._sweep(now)
        if h.start and h.end:
            return [data]
        key = h.key
        if h.start:
            self._rx.pop(key, None)  # a new transfer restarts this one (libcanard does the same)
            limit = None if h.source == 0 else self.max_bytes(h.data_type_id, h.service, h.request)
            if limit is None or len(self._rx) >= self.max_transfers:
                self.dropped += 1  # unknown type / anonymous multi-frame / no room: nothing buffered
                return None
            frames = -(-(limit + CRC_BYTES) // FRAME_PAYLOAD)
            self._rx[key] = _Partial(can_id, h.transfer_id, now, frames, [data])
            return None
        p = self._rx.get(key)
        if p is None or h.transfer_id != p.transfer_id or h.toggle != p.next_toggle:
            self.ignored += 1
            return None
        if now - p.started > self.timeout_s:
            del self._rx[key]
            self.timed_out += 1
            return None
        if len(p.frames) >= p.max_frames:
            del self._rx[key]  # longer than its type can be: a forgery or a corrupt stream
            self.dropped += 1
            return None
        p.frames.append(data)
        p.next_toggle = not p.next_toggle
        if h.end:
            del self._rx[key]
            return p.frames
        return None

    def _sweep(self, now: float) -> None:
        """Forget transfers older than the timeout (at most every tenth of the timeout)."""
        if now < self._next_sweep:
            return
        self._next_sweep = now + self.timeout_s / 10
        for key in [k for k, p in self._rx.items() if now - p.started > self.timeout_s]:
            del self._rx[key]
            self.timed_out += 1


class AnswerQueue:
    """Pending answers, one per requesting node, released at a bounded rate (a token bucket)."""

    def __init__(self, *, per_call: int = ANSWERS_PER_TICK, per_s: float = ANSWERS_PER_S,
                 max_pending: int = MAX_PENDING) -> None:
        self.per_call, self.per_s, self.max_pending = per_call, per_s, max_pending
        self._pending: OrderedDict[int, Any] = OrderedDict()
        self._tokens = float(per_call)
        self._t: float | None = None
        self.dropped = 0

    def add(self, requester: int, request: Any) -> None:
        if requester not in self._pending and len(self._pending) >= self.max_pending:
            self.dropped += 1
        else:
            self._pending[requester] = request  # a node's newest request replaces its older one (transfer id)

    def due(self, now: float) -> list[Any]:
        if self._t is not None:
            self._tokens = min(max(self.per_call, 1.0), self._tokens + (now - self._t) * self.per_s)
        self._t = now
        out: list[Any] = []
        while self._pending and len(out) < self.per_call and self._tokens >= 1.0 - 1e-9:
            out.append(self._pending.popitem(last=False)[1])
            self._tokens -= 1.0
        return out


@functools.cache
def dsdl_max_bytes(data_type_id: int, service: bool, request: bool) -> int | None:
    """The largest encoding of a DSDL type in bytes (the dronecan library's max bit length), None if unknown."""
    kind = 0 if service else 1  # dsdl.CompoundType.KIND_SERVICE, KIND_MESSAGE
    t = dronecan.DATATYPES.get((data_type_id, kind))
    if t is None:
        return None
    bits = (t.get_max_bitlen_request() if request else t.get_max_bitlen_response()) if service \
        else t.get_max_bitlen()
    return (int(bits) + 7) // 8


class DroneCanEngine:
    """One DroneCAN node's protocol state: transfer ids, reassembly, NodeStatus, GetNodeInfo, collisions."""

    def __init__(self, node_id: int, name: str, *, clock: Any = time.monotonic,
                 software: tuple[int, int] = (0, 1)) -> None:
        if not 1 <= node_id <= 125:
            raise ValueError(f"DroneCAN node id {node_id}: expected 1..125")
        self.node_id = node_id
        self.name = name
        self.clock = clock
        self.t0: float | None = None  # the robot's clock when the node first spoke: uptime counts from it
        self.health = 0  # HEALTH_OK
        self.mode = 0  # MODE_OPERATIONAL
        self._next_status: float | None = None  # the first periodic() call sends at once
        self._transfer_ids: dict[int, int] = {}
        self.rx = Reassembler(dsdl_max_bytes)
        self.answers = AnswerQueue()
        self._sent: deque[tuple[int, bytes]] = deque(maxlen=ECHO_FRAMES)
        self._software = software
        self.bad_transfers = 0
        self.answered_info = 0
        self.nodes_seen: dict[int, tuple[int, int]] = {}  # node id -> (health, mode) of its last NodeStatus
        self.collision_frames = 0  # frames from another node with our node id
        self._collision: tuple[float, str] | None = None  # (when, what) of the last one

    # --- in ----------------------------------------------------------------------------
    def take(self, msg: can.Message, now: float | None = None) -> Any | None:
        """A complete transfer (dronecan.transport.Transfer) once its last frame is in, else None.
        `now`: the robot's clock in seconds (the engine's clock when None), for the transfer
        timeout and the collision's age. GetNodeInfo requests to us are queued for `outgoing`."""
        if not msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame or not msg.data:
            return None
        t = self.clock() if now is None else now
        data = bytes(msg.data)
        head = FrameHeader.parse(msg.arbitration_id, data)
        if head.source == self.node_id and (msg.arbitration_id, data) not in self._sent:
            self._note_collision(head, t)
        parts = self.rx.push(msg.arbitration_id, data, t, head)
        if parts is None:
            return None
        tr = transport.Transfer()
        try:
            tr.from_frames([transport.Frame(msg.arbitration_id, d, ts_monotonic=t) for d in parts])
        except Exception:  # an unknown type, a bad CRC, a forged tail byte: counted, never raised
            self.bad_transfers += 1
            return None
        if (tr.service_not_message and tr.request_not_response and tr.dest_node_id == self.node_id
                and type_name(tr) == "uavcan.protocol.GetNodeInfo"):
            self.answers.add(tr.source_node_id, tr)
        elif not tr.service_not_message and type_name(tr) == "uavcan.protocol.NodeStatus":
            self.nodes_seen[tr.source_node_id] = (int(tr.payload.health), int(tr.payload.mode))
        return tr

    def _note_collision(self, head: FrameHeader, now: float) -> None:
        kind = 0 if head.service else 1
        t = dronecan.DATATYPES.get((head.data_type_id, kind))
        what = (t.full_name if t is not None else f"data type {head.data_type_id}") + (
            (" request" if head.request else " response") if head.service else "")
        self.collision_frames += 1
        self._collision = (now, what)

    def collision(self, now: float | None = None, hold_s: float = COLLISION_HOLD_S) -> str:
        """Words for a STATUSTEXT while another node uses our node id (its last frame within
        `hold_s`), '' otherwise."""
        if self._collision is None:
            return ""
        t = self.clock() if now is None else now
        when, what = self._collision
        if t - when > hold_s:
            return ""
        return (f"DroneCAN node id {self.node_id} used by another node ({what} from it "
                f"{max(0.0, t - when):.1f} s ago): give one of them another id")

    def _answer_node_info(self, req: Any, now: float) -> list[can.Message]:
        resp = dronecan.uavcan.protocol.GetNodeInfo.Response()
        self._fill_status(resp.status, now)
        resp.software_version.major, resp.software_version.minor = self._software
        resp.name = self.name
        out = transport.Transfer(payload=resp, source_node_id=self.node_id, dest_node_id=req.source_node_id,
                                 transfer_id=req.transfer_id, transfer_priority=req.transfer_priority,
                                 service_not_message=True, request_not_response=False)
        self.answered_info += 1
        return [self._msg(f) for f in out.to_frames()]

    # --- out ---------------------------------------------------------------------------
    def broadcast(self, payload: Any, priority: int = PRIORITY_DEFAULT) -> list[can.Message]:
        dtid = dronecan.get_dronecan_data_type(payload).default_dtid
        tid = self._transfer_ids.get(dtid, 0)
        self._transfer_ids[dtid] = (tid + 1) % 32
        tr = transport.Transfer(payload=payload, source_node_id=self.node_id, transfer_id=tid,
                                transfer_priority=priority, service_not_message=False)
        return [self._msg(f) for f in tr.to_frames()]

    def periodic(self, now: float | None = None) -> list[can.Message]:
        """NodeStatus when it is due (1 Hz on `now`, the robot's clock: sim time in HIL, as every
        other period and timeout), else nothing."""
        now = self.clock() if now is None else now
        due = self._next_status
        if due is not None and now < due:
            return []
        self._next_status = now + NODE_STATUS_PERIOD_S if due is None else max(due + NODE_STATUS_PERIOD_S, now)
        status = dronecan.uavcan.protocol.NodeStatus()
        self._fill_status(status, now)
        return self.broadcast(status, PRIORITY_LOW)

    def outgoing(self, now: float | None = None) -> list[can.Message]:
        """The answers due now: at most ANSWERS_PER_TICK a call, ANSWERS_PER_S a second. Send them
        after the tick's wheel command."""
        t = self.clock() if now is None else now
        return [m for req in self.answers.due(t) for m in self._answer_node_info(req, t)]

    def _fill_status(self, status: Any, now: float) -> None:
        if self.t0 is None:
            self.t0 = now
        status.uptime_sec = int(now - self.t0)
        status.health = self.health
        status.mode = self.mode

    def _msg(self, frame: Any) -> can.Message:
        data = bytes(frame.bytes)
        self._sent.append((frame.message_id, data))
        return can.Message(arbitration_id=frame.message_id, data=data, is_extended_id=True)


def type_name(transfer: Any) -> str:
    return str(dronecan.get_dronecan_data_type(transfer.payload).full_name)
