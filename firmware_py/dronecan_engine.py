"""The robot as a DroneCAN node: a pure engine on the `dronecan` library's DSDL and framing.

The `dronecan` library (the optional extra `qnav[dronecan]`) serialises DSDL types and splits and
reassembles transfers (`dronecan.transport.Transfer`, `TransferManager`). Its `Node` owns a driver
and a thread of its own; here the robot's node owns the bus, and the control tick must send its
wheel command in order with the tick's other frames (in lockstep HIL, before the tick's answer).
So this engine does no I/O: `take(msg)` reassembles a received 29-bit frame into a transfer (and
queues the answer to a GetNodeInfo request addressed to us), `broadcast(payload)` returns the frames
of a message, `periodic(now)` the NodeStatus due at 1 Hz, and `outgoing()` the queued answers; the
backends (drives/dronecan.py, sensors) and the node's shell move the frames.

Standard ids only ever come from qnav's own frames and ODrives; every DroneCAN frame is extended.
"""

from __future__ import annotations

import time
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


class DroneCanEngine:
    """One DroneCAN node's protocol state: transfer ids, reassembly, NodeStatus, GetNodeInfo."""

    def __init__(self, node_id: int, name: str, *, clock: Any = time.monotonic,
                 software: tuple[int, int] = (0, 1)) -> None:
        if not 1 <= node_id <= 125:
            raise ValueError(f"DroneCAN node id {node_id}: expected 1..125")
        self.node_id = node_id
        self.name = name
        self.clock = clock
        self.t0 = clock()
        self.health = 0  # HEALTH_OK
        self.mode = 0  # MODE_OPERATIONAL
        self._next_status = self.t0
        self._transfer_ids: dict[int, int] = {}
        self._manager = transport.TransferManager()
        self._out: list[can.Message] = []
        self._software = software
        self.bad_transfers = 0
        self.answered_info = 0
        self.nodes_seen: dict[int, tuple[int, int]] = {}  # node id -> (health, mode) of its last NodeStatus

    # --- in ----------------------------------------------------------------------------
    def take(self, msg: can.Message) -> Any | None:
        """A complete transfer (dronecan.transport.Transfer) once its last frame is in, else None.
        Requests to us that the engine answers itself (GetNodeInfo) are answered here."""
        if not msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame or not msg.data:
            return None
        frame = transport.Frame(msg.arbitration_id, bytes(msg.data), ts_monotonic=self.clock())
        frames = self._manager.receive_frame(frame)
        if not frames:
            return None
        tr = transport.Transfer()
        try:
            tr.from_frames(frames)
        except Exception:  # an unknown type, a bad CRC, a forged tail byte: counted, never raised
            self.bad_transfers += 1
            return None
        if (tr.service_not_message and tr.request_not_response and tr.dest_node_id == self.node_id
                and type_name(tr) == "uavcan.protocol.GetNodeInfo"):
            self._answer_node_info(tr)
        elif not tr.service_not_message and type_name(tr) == "uavcan.protocol.NodeStatus":
            self.nodes_seen[tr.source_node_id] = (int(tr.payload.health), int(tr.payload.mode))
        return tr

    def _answer_node_info(self, req: Any) -> None:
        resp = dronecan.uavcan.protocol.GetNodeInfo.Response()
        self._fill_status(resp.status)
        resp.software_version.major, resp.software_version.minor = self._software
        resp.name = self.name
        out = transport.Transfer(payload=resp, source_node_id=self.node_id, dest_node_id=req.source_node_id,
                                 transfer_id=req.transfer_id, transfer_priority=req.transfer_priority,
                                 service_not_message=True, request_not_response=False)
        self._out += [self._msg(f) for f in out.to_frames()]
        self.answered_info += 1

    # --- out ---------------------------------------------------------------------------
    def broadcast(self, payload: Any, priority: int = PRIORITY_DEFAULT) -> list[can.Message]:
        dtid = dronecan.get_dronecan_data_type(payload).default_dtid
        tid = self._transfer_ids.get(dtid, 0)
        self._transfer_ids[dtid] = (tid + 1) % 32
        tr = transport.Transfer(payload=payload, source_node_id=self.node_id, transfer_id=tid,
                                transfer_priority=priority, service_not_message=False)
        return [self._msg(f) for f in tr.to_frames()]

    def periodic(self) -> list[can.Message]:
        """NodeStatus when it is due (1 Hz), else nothing."""
        now = self.clock()
        if now < self._next_status:
            return []
        self._next_status = max(self._next_status + NODE_STATUS_PERIOD_S, now)
        status = dronecan.uavcan.protocol.NodeStatus()
        self._fill_status(status)
        return self.broadcast(status, PRIORITY_LOW)

    def outgoing(self) -> list[can.Message]:
        out, self._out = self._out, []
        return out

    def _fill_status(self, status: Any) -> None:
        status.uptime_sec = int(self.clock() - self.t0)
        status.health = self.health
        status.mode = self.mode

    @staticmethod
    def _msg(frame: Any) -> can.Message:
        return can.Message(arbitration_id=frame.message_id, data=bytes(frame.bytes), is_extended_id=True)


def type_name(transfer: Any) -> str:
    return str(dronecan.get_dronecan_data_type(transfer.payload).full_name)
