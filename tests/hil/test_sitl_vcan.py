"""`qnav sitl --can socketcan:vcan0` on a kernel vcan0 (this kernel's, else
user-mode Linux via ground_station/lab/rigs/vcan.py; skipped with the reason
where neither exists): the bring-up comes up, a separate pymavlink client
sees the robot's HEARTBEAT, `candump -L vcan0` records the sim's and the
robot's frames (decoded with cantools and firmware_py/qnav.dbc), and the run
stops cleanly after --duration."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from ground_station.subprocs import free_udp_port
from tests.support.vcan import kernel_vcan

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent

PROBE = """
import json, os, sys, time
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil
out, port = sys.argv[1], sys.argv[2]
deadline = time.monotonic() + 120
while time.monotonic() < deadline and "Ctrl-C stops every process" not in open(out + "/sitl.out").read():
    time.sleep(0.5)
conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=250)
M = mavutil.mavlink
seen = None
while time.monotonic() < deadline and seen is None:
    conn.mav.heartbeat_send(M.MAV_TYPE_ONBOARD_CONTROLLER, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    seen = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=1)
json.dump(None if seen is None else {"sysid": seen.get_srcSystem(), "type": seen.type,
                                     "custom_mode": seen.custom_mode}, open(out + "/heartbeat.json", "w"))
"""


@pytest.mark.slow
@pytest.mark.vcan
@pytest.mark.timeout(400)
def test_sitl_on_socketcan_vcan0_heartbeat_and_candump(tmp_path):
    if not shutil.which("candump"):
        pytest.skip("can-utils (candump) not installed")
    vcan = kernel_vcan()
    out = tmp_path / "sitl"
    out.mkdir()
    (out / "probe.py").write_text(PROBE)
    env = {k: os.environ[k] for k in ("PYTHONPATH", "HOME", "LANG") if k in os.environ}
    env["PYTHONPATH"] = f"{ROOT}{os.pathsep}{env.get('PYTHONPATH', '')}"
    env["PATH"] = f"{BIN}:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
    ch = vcan.channel
    port = free_udp_port()  # free here; inside UML its own loopback is empty anyway
    script = f"""
candump -L {ch} > {out}/sitl.candump &
CANDUMP=$!
{sys.executable} -m ground_station.cli sitl --can {vcan.can_spec} --mavlink udpin:127.0.0.1:{port} \\
    --out {out}/run --duration 10 > {out}/sitl.out 2>&1 &
SITL=$!
{sys.executable} {out}/probe.py {out} {port}
wait $SITL
echo $? > {out}/sitl_exit
kill $CANDUMP
wait $CANDUMP
exit 0
"""
    run = vcan.run(script, out / "vcan", cwd=ROOT, env=env, timeout_s=360)
    assert run.exit_status == 0, run.describe()
    text = (out / "sitl.out").read_text()
    assert (out / "sitl_exit").read_text().strip() == "0", text
    assert f"CAN bus: socketcan:{ch}" in text and f"candump -L {ch}" in text and "robot sysid 1 up" in text, text
    assert "every process stopped" in text, text
    hb = json.loads((out / "heartbeat.json").read_text())
    assert hb == {"sysid": 1, "type": 10, "custom_mode": 4}  # GROUND_ROVER in Hold
    lines = (out / "sitl.candump").read_text().splitlines()
    assert len(lines) > 100 and all(f" {ch} " in ln for ln in lines[:20]), lines[:3]
    decoded = subprocess.run([str(BIN / "cantools"), "decode", str(ROOT / "firmware_py" / "qnav.dbc")],
                             input="\n".join(lines) + "\n", capture_output=True, text=True, check=True).stdout
    for name in ("SimTick(", "RangeSectors0(", "EncoderCounts(", "ControllerHeartbeat("):
        assert name in decoded, name
    print(f"qnav sitl on {vcan.can_spec} ({vcan.where}): {len(lines)} frames, {run.wall_s:.1f} s wall")
