"""Reading a Foxglove WebSocket server's frames as a client (ws-protocol: JSON ops as text, message data
as binary frames of opcode 0x01, subscription id u32, timestamp u64, payload)."""

from __future__ import annotations

import asyncio
import json
import struct
import time
from collections.abc import AsyncIterator, Callable


async def frames(ws, seconds: float, recv_s: float,
                 done: Callable[[], object] = lambda: False) -> AsyncIterator[tuple[list[dict], int | None, bytes]]:
    """(advertised channels, None, b"") for each `advertise` op and ([], subscription id, payload) for each
    message data frame, until `done()` or `seconds` pass (a receive waits `recv_s` at the most)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end and not done():
        try:
            raw = await asyncio.wait_for(ws.recv(), recv_s)
        except TimeoutError:
            continue
        if isinstance(raw, str):
            doc = json.loads(raw)
            if doc.get("op") == "advertise":
                yield doc["channels"], None, b""
        elif raw[0] == 0x01:
            yield [], struct.unpack_from("<I", raw, 1)[0], raw[13:]
