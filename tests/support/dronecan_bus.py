"""A `dronecan` library driver on an already open python-can bus, for the tests' stock DroneCAN nodes
(the node monitor). The library's own python-can driver opens its bus by name and, in 1.0.27, cannot
run on a python-can-remote hub: its writer thread calls `flush_tx_buffer` (which that bus lacks) and
it passes its receive timeout in milliseconds where python-can takes seconds."""

from __future__ import annotations

import can
from dronecan.driver.common import AbstractDriver, CANFrame

from firmware_py.dronecan_engine import AnswerQueue, Reassembler


def in_progress(rx: Reassembler) -> int:
    """How many multi-frame transfers `rx` is reassembling."""
    return len(rx._rx)


def buffered_bytes(rx: Reassembler) -> int:
    """The frame bytes `rx` holds for its unfinished transfers."""
    return sum(len(b) for p in rx._rx.values() for b in p.frames)


def waiting(q: AnswerQueue) -> int:
    """How many requesting nodes wait for an answer."""
    return len(q._pending)


class PythonCanBusDriver(AbstractDriver):
    def __init__(self, bus: can.BusABC) -> None:
        super().__init__()
        self.bus = bus

    def receive(self, timeout: float | None = None) -> CANFrame | None:
        msg = self.bus.recv(timeout=0 if timeout is None else timeout)
        if msg is None or not msg.is_extended_id:
            return None  # qnav's and ODrive's standard frames are not DroneCAN's
        frame = CANFrame(msg.arbitration_id, bytearray(msg.data), True)
        self._rx_hook(frame)
        return frame

    def send_frame(self, frame: CANFrame) -> None:
        self.bus.send(can.Message(arbitration_id=frame.id, data=bytes(frame.data), is_extended_id=True))
        self._tx_hook(frame)

    def close(self) -> None:
        self.bus.shutdown()
