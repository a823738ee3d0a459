"""The Foxglove live bridge as a back door (issue 43, finding 2), one scenario.

`bridge_holes`: the real processes in paced HIL (a python-can-remote hub,
`qnav-sim --realtime`, `qnav-robot --sim-clock` with the shipped paper10 cell
policy, MAVLink on UDP loopback), armed by an operator's link (another
ground station: `ground_station.mavlink.link.Link`, its GCS failsafe off so
that monitors may come and go between trials). Each trial starts a real
`qnav monitor --plain --foxglove` on a free port, puts the robot in Hold or
Guided from the operator's link, and lets a stock WebSocket client (the
`websockets` package speaking foxglove.sdk.v1) try to publish a goal on
`/goal`; what the monitor's own status lines say (mode, controller state,
pose) for the next seconds is the verdict. Trial i is CASES[(first + i) % 7]:

- `evil_origin_hold`: `--foxglove-goals`, the client sends
  `Origin: http://evil.example` (what any web page in the operator's browser
  sends to 127.0.0.1), the robot armed in Hold: the handshake is refused
  (HTTP 403), Hold stays Hold, the robot does not move (< 5 cm, never
  DRIVING). Before the fix the goal went through: Hold -> Guided, driving.
- `evil_origin_guided`: the same page while the operator has Guided on: 403,
  no motion (the origin check alone holds).
- `read_only_guided`: no `--foxglove-goals`, no Origin, robot in Guided: the
  server offers no publishing, no goal is sent, no motion.
- `no_token_guided`: `--foxglove-goals --foxglove-token T`, a client without
  the token, robot in Guided: HTTP 401, no motion.
- `goal_in_hold`: `--foxglove-goals`, no Origin, robot in Hold: the bridge
  drops the goal and says so ("... dropped: the robot is in Hold, not
  Guided" on stderr and /log), Hold stays, no motion.
- `target_in_hold`: no bridge: the operator's link itself sends the
  SET_POSITION_TARGET_LOCAL_NED the bridge would send (a bridge whose view of
  the mode is stale) in Hold: the robot refuses it ("goal refused: mode
  Hold, not Guided"), Hold stays, no motion.
- `guided_goal` (the positive control, so the others are not vacuous):
  `--foxglove-goals --foxglove-token T`, the client gives the token in the
  URL, no Origin, the operator has set Guided: the goal is forwarded and the
  robot drives (> 0.2 m within 8 s); the operator then sets Hold.
"""

from __future__ import annotations

import asyncio
import json
import math
import re
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ground_station.lab.faults.common import RobotProcess, ScenarioResult, register, trials
from ground_station.subprocs import exit_code

CASES = ("evil_origin_hold", "evil_origin_guided", "read_only_guided", "no_token_guided", "goal_in_hold",
         "target_in_hold", "guided_goal")
EVIL_ORIGIN = "http://evil.example"
TOKEN = "qnav-bridge-holes"
HOLD, GUIDED = 4, 15  # Rover custom modes (firmware_py.vehicle.Mode)
OPERATOR_COMPONENT = 26  # the operator's other ground station (as the HIL bridge test arms from)
# how long each trial watches the robot after the publish: the positive control (a goal in Guided) shows
# 0.2 m of motion in the monitor's 1 Hz status lines 1.5 s after its publish, a refused one must show none
WATCH_S = 2.5
STILL_M = 0.05
MOVED_M = 0.2
_STATUS = re.compile(r"mode=(\S+) armed=(\S+) ctrl=(\S+).* x=(\S+) y=(\S+)")


@contextmanager
def _robot(tmp: Path, seed: int, duration_s: float) -> Iterator[Any]:
    """Hub + qnav-sim --realtime + qnav-robot --sim-clock on paper10, no goals: the RobotProcess. The
    sim runs `duration_s` of sim time (its default, 60 s, ended the robot after 7 bench trials)."""
    from firmware_py import robot_spec as rb
    from firmware_py.storage import ACTIVE_POLICY, Storage
    from ground_station.canhub import CanHub
    from ground_station.lab.rigs.lockstep import CELL_POLICY, paper10
    from ground_station.processes import ChildProcess, qnav_sim

    gm = paper10()
    storage_dir = tmp / f"robot-{seed}"
    Storage(storage_dir).write_atomic(ACTIVE_POLICY, CELL_POLICY.read_bytes())
    x, y = rb.cell_center_mm(0, 9, gm.height)
    with CanHub(f"bridge{seed}") as hub:
        sim = ChildProcess(qnav_sim("--map", "paper10", "--can", hub.spec, "--realtime", "--duration", f"{duration_s:g}", "--start",
                                    f"{x / 1000},{y / 1000},90", "-q"), tmp / f"sim-{seed}.log")
        robot = RobotProcess(storage_dir, can=hub.spec, extra=["--sim-clock", "--start-cell", "0,9,90", "-q"],
                             log=tmp / f"robot-{seed}.log")
        sim.start()
        try:
            robot.start()
            yield robot
        finally:
            robot.stop()
            sim.stop(grace_s=10)


class _Operator:
    """The operator's own ground station: arm, modes, a raw position target."""

    def __init__(self, url: str) -> None:
        from ground_station.mavlink.link import GCS_SYSID, Link

        self.link = Link(url, tlog=False, name="operator", source_system=GCS_SYSID,
                         source_component=OPERATOR_COMPONENT)
        self.link.connect(30)
        self.m = self.link.m

    def setup(self) -> None:
        self.link.param_set("FS_GCS_ENABLE", 0)  # monitors come and go between trials
        deadline = time.monotonic() + 30
        while True:  # the sensors must be fresh before it arms
            res = self.link.command(self.m.MAV_CMD_COMPONENT_ARM_DISARM, 1, check=False)
            if res.result == self.m.MAV_RESULT_ACCEPTED:
                return
            if time.monotonic() > deadline:
                raise RuntimeError(f"the robot did not arm: {res.texts}")
            time.sleep(0.5)

    def mode(self, mode: int) -> None:
        self.link.command(self.m.MAV_CMD_DO_SET_MODE, self.m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)

    def position_target(self, x_m: float, y_m: float) -> str:
        """SET_POSITION_TARGET_LOCAL_NED as the bridge sends it; the robot's refusal text ("" if none)."""
        since = len(self.link.texts)
        self.link.conn.mav.set_position_target_local_ned_send(0, self.link.sysid, self.link.compid,
                                                              self.m.MAV_FRAME_LOCAL_NED, 0xFFF8, y_m, x_m, 0,
                                                              0, 0, 0, 0, 0, 0, 0, 0)
        return self.link.wait_text(since, lambda t: t.startswith("goal refused"), 2.0) or ""

    def drain(self) -> None:
        """Forget what queued up while a monitor had the robot's replies."""
        while self.link.conn.recv_match(blocking=False) is not None:
            pass

    def close(self) -> None:
        self.link.close()


class _Monitor:
    """`qnav monitor --plain --foxglove` as a child process; its status lines parsed."""

    def __init__(self, robot_port: int, ws_port: int, flags: list[str], cwd: Path) -> None:
        from ground_station.processes import program_argv

        self.proc = subprocess.Popen(
            [*program_argv("ground_station.cli:main", "qnav"), "monitor", "--plain", "--foxglove", "--port",
             str(ws_port), "--mavlink", f"udpout:127.0.0.1:{robot_port}", "--no-tlog", "--map", "paper10",
             "--duration", "120", *flags],
            cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.status: list[tuple[float, str, str, float, float]] = []  # (wall, mode, ctrl, x, y)
        self.errors: list[str] = []
        self._lock = threading.Lock()
        threading.Thread(target=self._read_out, daemon=True).start()
        threading.Thread(target=self._read_err, daemon=True).start()

    def _read_out(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            m = _STATUS.search(line)
            if m is None:
                continue
            try:
                x, y = float(m.group(4)), float(m.group(5))
            except ValueError:
                continue
            with self._lock:
                self.status.append((time.monotonic(), m.group(1), m.group(3), x, y))

    def _read_err(self) -> None:
        assert self.proc.stderr is not None
        for line in self.proc.stderr:
            with self._lock:
                self.errors.append(line.rstrip())

    def stderr_has(self, text: str) -> bool:
        with self._lock:
            return any(text in line for line in self.errors)

    def since(self, t: float) -> list[tuple[float, str, str, float, float]]:
        with self._lock:
            return [s for s in self.status if s[0] >= t]

    def wait_ready(self, timeout_s: float = 60.0) -> str:
        """'' once the bridge serves and a status line shows the robot; else why not."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if (code := exit_code(self.proc)) is not None:
                return f"qnav monitor exited {code}: {' | '.join(self.errors[-3:])}"
            if self.stderr_has("Foxglove bridge on ws://") and self.status:
                return ""
            time.sleep(0.1)
        return "qnav monitor: no bridge or no robot status within 60 s"

    def wait_mode(self, mode: str, timeout_s: float = 5.0) -> bool:
        t0 = time.monotonic()
        while time.monotonic() < t0 + timeout_s:
            if any(s[1] == mode for s in self.since(t0)):
                return True
            time.sleep(0.1)
        return False

    def stop(self) -> None:
        from ground_station.subprocs import stop_process

        stop_process(self.proc, timeout_s=20)


async def _publish(ws_port: int, origin: str | None, token: str | None, goal: tuple[float, float]) -> str:
    """Connect as a Foxglove client and publish one goal; 'published', or 'refused: ...'."""
    import websockets
    from websockets.typing import Subprotocol

    kw: dict[str, Any] = {"origin": origin} if origin is not None else {}
    url = f"ws://127.0.0.1:{ws_port}/" + (f"?token={token}" if token is not None else "")
    try:
        async with websockets.connect(url, subprotocols=[Subprotocol("foxglove.sdk.v1")], max_size=None,
                                      **kw) as ws:
            info = json.loads(await asyncio.wait_for(ws.recv(), 10))
            await ws.send(json.dumps({"op": "advertise", "channels": [
                {"id": 7, "topic": "/goal", "encoding": "json", "schemaName": "qnav.Goal"}]}))
            await asyncio.sleep(0.3)
            await ws.send(b"\x01" + struct.pack("<I", 7) + json.dumps({"x": goal[0], "y": goal[1]}).encode())
            await asyncio.sleep(0.5)
            return f"published (capabilities {info.get('capabilities')})"
    except websockets.exceptions.InvalidStatus as exc:
        return f"refused: HTTP {exc.response.status_code}"
    except (OSError, websockets.exceptions.WebSocketException, TimeoutError) as exc:
        return f"refused: {type(exc).__name__}: {exc}"


def _far_target(x: float, y: float) -> tuple[float, float]:
    """The paper10 target farthest from (x, y) metres (a goal of the shipped cell policy)."""
    from firmware_py import robot_spec as rb
    from ground_station.lab.rigs.lockstep import paper10

    gm = paper10()
    cells = [rb.cell_center_mm(c, r, gm.height) for c, r in gm.targets.values()]
    bx, by = max(cells, key=lambda p: math.hypot(p[0] / 1000 - x, p[1] / 1000 - y))
    return bx / 1000, by / 1000


def _trial(case: str, robot_port: int, op: _Operator, tmp: Path, figures: dict[str, Any]) -> list[str]:
    from ground_station.subprocs import free_port

    problems: list[str] = []
    want_mode = HOLD if case in ("evil_origin_hold", "goal_in_hold", "target_in_hold") else GUIDED
    mode_name = "Hold" if want_mode == HOLD else "Guided"
    op.mode(want_mode)
    if case == "target_in_hold":
        op.drain()
        hb = op.link.recv("LOCAL_POSITION_NED", 3.0)
        before = (hb.y, hb.x) if hb is not None else (0.0, 0.0)  # NED -> east, north
        refusal = op.position_target(*_far_target(*before))
        figures["robot_answer_in_hold"] = refusal or "none"
        if "mode Hold, not Guided" not in refusal:
            problems.append(f"the robot's answer to a position target in Hold: {refusal or 'none'}")
        time.sleep(WATCH_S)
        op.drain()
        hb2 = op.link.recv("HEARTBEAT", 3.0, cond=lambda m: m.type != 6)
        pos = op.link.recv("LOCAL_POSITION_NED", 3.0)
        if hb2 is None or hb2.custom_mode != HOLD:
            problems.append(f"mode {getattr(hb2, 'custom_mode', None)} after the refused target, not Hold")
        if pos is not None and math.hypot(pos.y - before[0], pos.x - before[1]) > STILL_M:
            problems.append(f"moved {math.hypot(pos.y - before[0], pos.x - before[1]):.2f} m")
        return problems
    flags = {"evil_origin_hold": ["--foxglove-goals"], "evil_origin_guided": ["--foxglove-goals"],
             "read_only_guided": [], "no_token_guided": ["--foxglove-goals", "--foxglove-token", TOKEN],
             "goal_in_hold": ["--foxglove-goals"],
             "guided_goal": ["--foxglove-goals", "--foxglove-token", TOKEN]}[case]
    ws_port = free_port()
    mon = _Monitor(robot_port, ws_port, flags, tmp)
    try:
        why = mon.wait_ready()
        if why:
            return [why]
        if not mon.wait_mode(mode_name, 6.0):
            op.mode(want_mode)  # the operator's ACK may have gone to the monitor: once more
            if not mon.wait_mode(mode_name, 6.0):
                return [f"the robot is not in {mode_name} before the publish"]
        _t, _mode, _ctrl, x0, y0 = mon.since(0)[-1]
        goal = _far_target(x0, y0)
        t0 = time.monotonic()
        origin = EVIL_ORIGIN if case.startswith("evil_origin") else None
        outcome = asyncio.run(_publish(ws_port, origin, TOKEN if case == "guided_goal" else None, goal))
        figures.setdefault("clients", {})[case] = outcome
        time.sleep(WATCH_S if case != "guided_goal" else 0.0)
        if case == "guided_goal":  # the positive control: it drives
            end = time.monotonic() + 8.0
            moved = 0.0
            while time.monotonic() < end and moved <= MOVED_M:
                time.sleep(0.5)
                moved = max((math.hypot(s[3] - x0, s[4] - y0) for s in mon.since(t0)), default=0.0)
            figures.setdefault("moved_m", {})[case] = round(moved, 2)
            if not outcome.startswith("published"):
                problems.append(f"the client was refused: {outcome}")
            if moved <= MOVED_M:
                problems.append(f"the goal forwarded in Guided did not drive the robot ({moved:.2f} m in 8 s)")
            op.mode(HOLD)
            return problems
        seen = mon.since(t0)
        moved = max((math.hypot(s[3] - x0, s[4] - y0) for s in seen), default=0.0)
        figures.setdefault("moved_m", {})[case] = round(moved, 2)
        if not seen:
            problems.append("no status line after the publish")
        if moved > STILL_M:
            problems.append(f"the robot moved {moved:.2f} m")
        if any(s[2] == "DRIVING" for s in seen):
            problems.append("the controller went DRIVING")
        modes = sorted({s[1] for s in seen})
        if modes and modes != [mode_name]:
            problems.append(f"mode {modes}, the operator set {mode_name}")
        if case.startswith("evil_origin") and outcome != "refused: HTTP 403":
            problems.append(f"a page from {EVIL_ORIGIN}: {outcome}")
        if case == "no_token_guided" and outcome != "refused: HTTP 401":
            problems.append(f"a client without the token: {outcome}")
        if case == "goal_in_hold" and not mon.stderr_has("dropped: the robot is in Hold, not Guided"):
            problems.append("the bridge did not say it dropped the goal")
        if mon.stderr_has("goal from Foxglove sent"):
            problems.append("the bridge sent the goal")
    finally:
        mon.stop()
    return problems


@register("bridge_holes", small=7, large=21, unit="bridge clients",
          what="Foxglove bridge: a page's Origin (403), no token (401), read-only default, goals in Hold dropped "
               "and refused by the robot: Hold stays Hold, no motion; a goal in Guided drives")
def bridge_holes(res: ScenarioResult, count: int, seed: int, progress: Any, first: int = 0) -> None:
    # each trial: a monitor's start, WATCH_S of watching and the operator's mode changes, ~6 s; trial i
    # is CASES[(first + i) % 7], so that cases can be split over robots run side by side
    with tempfile.TemporaryDirectory() as tmpdir, _robot(Path(tmpdir), seed, 60 + 20 * count) as robot:
        tmp = Path(tmpdir)
        op = _Operator(robot.url)
        try:
            op.setup()
            for i in trials(count, progress):
                case = CASES[(first + i) % len(CASES)]
                try:
                    problems = _trial(case, robot.port, op, tmp, res.figures)
                except Exception as exc:  # noqa: BLE001 - a broken trial is a lost trial, with its reason
                    problems = [f"{type(exc).__name__}: {exc}"]
                res.check(problems, f"{case} #{i}")
        finally:
            op.close()


if __name__ == "__main__":  # a quick look: python -m ground_station.lab.faults.bridge_holes [COUNT]
    r = bridge_holes(int(sys.argv[1]) if len(sys.argv) > 1 else len(CASES))
    print(json.dumps(r.as_dict(), indent=1))
