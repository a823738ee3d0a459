"""The drive-backend HIL matrix on a kernel SocketCAN vcan0 (the host's, or user-mode Linux), for the record.

Runs ground_station.lab.rigs.hil_scenarios' odrive_{goal,error,silent}, mission_odrive and the same for
dronecan in two batches side by side, then prints one line per scenario (exit codes, the robot's
result and FAULT text, the mission items reached). make test runs only the two error scenarios on vcan0
(its 8 minutes); this is the whole matrix (about 100 s in user-mode Linux).

    .venv/bin/python tools/vcan_backend_matrix.py [--out DIR]
"""
import json
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from ground_station.lab.rigs.vcan import find_vcan

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
vcan = find_vcan()
out = Path(sys.argv[sys.argv.index("--out") + 1] if "--out" in sys.argv else "runs/vcan-backend-matrix").resolve()
out.mkdir(parents=True, exist_ok=True)
env = {k: os.environ[k] for k in ("PYTHONPATH", "HOME", "LANG") if k in os.environ}
env["PATH"] = f"{BIN}:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
BATCHES = [["odrive_goal", "odrive_error", "odrive_silent", "mission_odrive"],
           ["dronecan_goal", "dronecan_error", "dronecan_silent", "mission_dronecan"]]
t0 = time.monotonic()


def run(i_names):
    i, names = i_names
    return vcan.run(f"{sys.executable} -m ground_station.lab.rigs.hil_scenarios --can {vcan.can_spec} --out {out} {' '.join(names)}",
                    out / f"run{i}", cwd=ROOT, env=env, timeout_s=900)
with ThreadPoolExecutor(2) as pool:
    runs = list(pool.map(run, enumerate(BATCHES)))
print("where", vcan.where, "wall", round(time.monotonic() - t0, 1))
for r in runs:
    print("exit", r.exit_status)
for names in BATCHES:
    for n in names:
        p = out / f"{n}.json"
        if not p.exists():
            print(n, "MISSING")
            continue
        d = json.loads(p.read_text())
        rob = d.get("robot") or {}
        print(n, {k: d.get(k) for k in ("robot_exit", "reached_seq", "error")}, rob.get("result"), rob.get("state"), (rob.get("fault") or "")[:90], rob.get("can_errors"), d.get("scenario_wall_s"))
