"""`qnav monitor --foxglove` on a `qnav sitl` whose world is not paper10 (issue 46, acceptance of
items 1 and 2): a WebSocket client connecting 10 s after the monitor started gets `/map` with the
robot's own map, read from the robot over MAVLink FTP (32x32 room-32-32-4, not paper10's 10x10), and
`/pose`, whichever subprotocol name it offers (`foxglove.websocket.v1`: Lichtblick, older Foxglove
Studio; `foxglove.sdk.v1`: Foxglove)."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time

import pytest

from ground_station.subprocs import free_port, stop_process
from tests.hil.test_foxglove_bridge import _decoder
from tests.hil.test_sitl import SitlProcess, child_env
from tests.support.foxglove_ws import frames

pytest.importorskip("websockets")


async def _late_client(ws_port: int, subprotocol: str) -> dict:
    import websockets

    got: dict = {"map": [], "pose": 0}
    async with websockets.connect(f"ws://127.0.0.1:{ws_port}", subprotocols=[subprotocol], max_size=None) as ws:
        got["subprotocol"] = ws.subprotocol
        channels: dict[int, dict] = {}
        async for advertised, sub, payload in frames(ws, 15, 1, lambda: got["map"] and got["pose"] >= 3):
            new = {c["id"]: c for c in advertised if c["topic"] in ("/map", "/pose")}
            channels.update(new)
            if new:
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": cid, "channelId": cid} for cid in new]}))
            if sub is None:
                continue
            if channels[sub]["topic"] == "/map":
                grid = _decoder(channels[sub]).FromString(payload)
                got["map"].append((grid.column_count, len(grid.data) // max(1, grid.row_stride)))
            else:
                got["pose"] += 1
    return got


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_a_client_10_s_late_gets_the_robots_own_map_and_pose_over_either_subprotocol(tmp_path):
    sitl = SitlProcess(tmp_path, "--map", "room-32-32-4", "--speed", "2")
    monitor = None
    try:
        sitl.wait_up()
        ws_port = free_port()
        monitor = subprocess.Popen(
            [sys.executable, "-m", "ground_station.cli", "monitor", "--plain", "--foxglove", "--port", str(ws_port),
             "--mavlink", f"udpout:127.0.0.1:{sitl.port}", "--no-tlog", "--duration", "120"],
            cwd=tmp_path, env=child_env(), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE, text=True)
        time.sleep(10.0)
        assert monitor.poll() is None
        results = {p: asyncio.run(_late_client(ws_port, p)) for p in ("foxglove.websocket.v1", "foxglove.sdk.v1")}
    finally:
        err = ""
        if monitor is not None:
            stop_process(monitor, timeout_s=20)
            err = monitor.stderr.read() if monitor.stderr else ""
        sitl.stop()
    for proto, got in results.items():
        assert got["subprotocol"] == proto, (proto, got)
        assert got["map"] and got["map"][0] == (32, 32), (proto, got["map"], err)
        assert got["pose"] >= 3, (proto, got)
    assert "showing the robot's map room-32-32-4" in err, err
