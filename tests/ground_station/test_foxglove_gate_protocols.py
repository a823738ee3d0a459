"""The live bridge's WebSocket side with a real `websockets` client (issue 46, items 1 and 2): a
client offering the ws-protocol spec's `foxglove.websocket.v1` (Lichtblick, older Foxglove Studio)
is served as one offering the SDK's `foxglove.sdk.v1` is, and /map is latched: a client that
subscribes long after the server started still gets it."""

from __future__ import annotations

import asyncio
import json
import threading
import time

import pytest

from ground_station.maps import load_map
from tests.support.foxglove_ws import frames

pytest.importorskip("websockets")
pytest.importorskip("foxglove")


def _with_bridge(body):
    from ground_station.logs.live import FoxgloveBridge

    bridge = FoxgloveBridge(0, load_map("room-32-32-4"))
    stop = threading.Event()

    def monitor_loop() -> None:  # what BridgedSource.poll does on the monitor's thread
        while not stop.wait(0.05):
            flush = getattr(bridge, "flush_map", None)
            if flush is not None:
                flush(time.time())

    loop = threading.Thread(target=monitor_loop, daemon=True)
    loop.start()
    try:
        return asyncio.run(body(bridge.port))
    finally:
        stop.set()
        loop.join()
        bridge.close()


async def _map_messages(port: int, subprotocol: str, wait_s: float) -> tuple[str | None, list[bytes]]:
    import websockets

    await asyncio.sleep(wait_s)  # the client comes late
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[subprotocol], max_size=None) as ws:
        got: list[bytes] = []
        async for channels, sub, payload in frames(ws, 5, 0.5, lambda: got):
            for ch in channels:
                if ch["topic"] == "/map":
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 5, "channelId": ch["id"]}]}))
            if sub == 5:
                got.append(payload)
        return ws.subprotocol, got


def test_a_client_offering_foxglove_websocket_v1_is_served_and_gets_the_latched_map():
    chosen, got = _with_bridge(lambda port: _map_messages(port, "foxglove.websocket.v1", 1.5))
    assert chosen == "foxglove.websocket.v1"
    assert len(got) == 1 and len(got[0]) > 32 * 32  # the 32x32 grid's cells are in the payload


def test_a_late_foxglove_sdk_v1_subscriber_gets_the_map():
    chosen, got = _with_bridge(lambda port: _map_messages(port, "foxglove.sdk.v1", 1.5))
    assert chosen == "foxglove.sdk.v1"
    assert len(got) == 1 and len(got[0]) > 32 * 32


def test_a_client_offering_another_subprotocol_is_still_refused():
    # websockets.exceptions is a submodule, an attribute only once something imported it (this test
    # failed so when it ran first on a worker): imported by name
    import websockets
    from websockets.exceptions import InvalidStatus

    async def body(port: int) -> None:
        with pytest.raises(InvalidStatus) as err:
            async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v2"]):
                pass
        assert err.value.response.status_code == 400

    _with_bridge(body)
