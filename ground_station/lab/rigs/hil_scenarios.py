"""HIL scenarios across processes on any CAN transport, as facts for a test to judge.

Each scenario starts the real programs (`qnav-sim`, `qnav-robot`, `qnav`) as
child processes on the bus named by a `--can` spec (a python-can-remote hub,
`socketcan:vcan0`, ...), stops every one of them, and returns a JSON-able
dict of what happened: exit codes, the robot's `--stats-json`, frames seen on
the bus. Assertions live in the tests (tests/test_hil_transports.py), the
same for every transport. Logs go to files in the scenario's work directory
(a pipe nobody reads would stall a program).

- `goal_reached`: lockstep, paper10, cell policy from (0.25, 0.25) to
  target B (cell 9,0); optionally `candump -L` records the bus meanwhile.
- `estop`: paced (sim time at `speed` x real time, robot on `--sim-clock`);
  once the robot's heartbeat says DRIVING an EStop frame is sent from another
  node (python-can, or `cansend` from the shell); the robot must command
  zero and exit 3 with "FAULT: e-stop engaged".
- `sensor_stop`: lockstep with this process as the plant (sim_bridge's
  Plant stepped here, frames sent on the bus); at 2 s the range boards and
  encoders go quiet; the robot must command zero and fault within the
  staleness timeout + one period.
- `mission`: lockstep sim + robot with its MAVLink node on UDP loopback; the
  ground-station side is the `qnav` command sequence an operator types:
  `qnav mission upload --targets A,B,C,D`, `qnav param set FS_GCS_ENABLE 0`
  (lockstep outruns a 1 Hz ground-station heartbeat), `qnav arm`, `qnav mode auto`
  (starts the mission), `qnav monitor --plain` recording a tlog (the
  caller may `qnav report` it). One command at a time, as a serial radio allows. The
  sim is paused (SIGSTOP: the world's clock stops, and with it the robot's)
  from the moment `qnav mode auto` answers until the monitor listens, so no
  MISSION_ITEM_REACHED passes unheard. `mission_ab`: the same with targets A,B.

Batch CLI (used inside user-mode Linux by tests/test_hil_transports.py):
    python -m ground_station.lab.rigs.hil_scenarios --can socketcan:vcan0 --out DIR \\
        goal_reached estop sensor_stop mission
writes DIR/<name>.json per scenario ({"error": ...} if it raised) and exits 0.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path

from firmware_py import can_protocol as cp
from firmware_py.canbus import open_bus
from firmware_py.kinds.sector.config import META_KEY as PLANNER_KEY
from firmware_py.mavlink.dialect import NAME as DIALECT
from firmware_py.policy import load_policy
from firmware_py.vehicle import CtrlState
from ground_station.learn.export import with_metadata
from ground_station.subprocs import exit_code, free_udp_port, stop_process

REPO = Path(__file__).resolve().parents[3]
BIN = Path(sys.executable).parent
CELL_POLICY = "policies/paper10_cell.qtab"
START = "0.25,0.25,0"
ESTOP_SIGNALS = {"EStop_Engage": 1, "EStop_Source": cp.NODE_SIM, "EStop_Reason": 1}


def estop_cansend_arg() -> str:
    """The `cansend` argument (`ID#HEXDATA`) of an engaged EStop from the sim's node id."""
    msg = cp.encode("EStop", ESTOP_SIGNALS)
    return f"{msg.arbitration_id:03X}#{bytes(msg.data).hex().upper()}"


class _Procs:
    """Child processes with their logs in `work`; every one stopped on exit."""

    def __init__(self, work: Path) -> None:
        self.work = work
        self.procs: list[subprocess.Popen] = []

    def start(self, name: str, cmd: list, env: dict | None = None, sig: int = signal.SIGINT) -> subprocess.Popen:
        with open(self.work / f"{name}.log", "wb") as log:
            p = subprocess.Popen([str(c) for c in cmd], stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                 cwd=REPO, env=dict(os.environ, MAVLINK20="1", PYTHONUNBUFFERED="1", **(env or {})))
        p.stop_signal = sig  # type: ignore[attr-defined]
        self.procs.append(p)
        return p

    def log(self, name: str) -> str:
        try:
            return (self.work / f"{name}.log").read_text(errors="replace")
        except OSError:
            return ""

    def __enter__(self) -> _Procs:
        return self

    def __exit__(self, *exc: object) -> None:
        for p in reversed(self.procs):
            with contextlib.suppress(ProcessLookupError):
                p.send_signal(signal.SIGCONT)  # a paused sim must be able to die
            # 30 s: a robot writes its --stats-json as it stops, which a CI run at 2 busy cores did not
            # reach within 10 s; a process that stops at once does not wait for it
            stop_process(p, timeout_s=30, sig=p.stop_signal)  # type: ignore[attr-defined]


def _wait(p: subprocess.Popen, timeout_s: float) -> int | None:
    try:
        return p.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return None


def _stats(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _sim_summary(text: str) -> dict | None:
    m = re.search(r"ticks (\d+) \(missed (\d+), stale commands (\d+)", text)
    return None if m is None else dict(zip(("ticks", "missed", "stale"), map(int, m.groups()), strict=True))


def _can_receivers(channel: str) -> int:
    """Raw CAN sockets bound on `channel` (the kernel's /proc/net/can/rcvlist_all; 0 without it)."""
    try:
        text = Path("/proc/net/can/rcvlist_all").read_text()
    except OSError:
        return 0
    return sum(1 for line in text.splitlines() if line.split()[:1] == [channel])


def _wait_for_receiver(channel: str, before: int, proc: subprocess.Popen, timeout_s: float = 15.0) -> None:
    """Until `proc` (candump) has its socket bound on `channel`: one more receiver than `before`.
    A fixed sleep lost the first SimTick's frames when user-mode Linux was slow to start it."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and exit_code(proc) is None:
        if _can_receivers(channel) > before:
            return
        time.sleep(0.02)
    if not Path("/proc/net/can/rcvlist_all").exists():
        time.sleep(0.5)  # no way to see the socket here: the old allowance


def _wait_still(path: Path, still_s: float, timeout_s: float) -> None:
    """Until `path` has not grown for `still_s` (or `timeout_s` passed)."""
    deadline = time.monotonic() + timeout_s
    size, since = -1, time.monotonic()
    while time.monotonic() < deadline:
        now_size = path.stat().st_size if path.exists() else 0
        if now_size != size:
            size, since = now_size, time.monotonic()
        elif time.monotonic() - since >= still_s:
            return
        time.sleep(0.1)


# the cell policy's trip to B takes ~33-35 s of sim time: 35 s left no margin once the collision monitor
# slowed it past block corners on the arc it drives (a fresh-clone make test ended 0.4 m short)
GOAL_DURATION_S = 40.0


def goal_reached(can: str, work: Path, *, duration_s: float = GOAL_DURATION_S, candump: str | None = None) -> dict:
    """Lockstep drive to target B; `candump` = channel to record with `candump -L` into goal.candump."""
    stats = work / "goal_robot.json"
    res: dict = {"scenario": "goal_reached", "can": can}
    with _Procs(work) as procs:
        dump = None
        if candump:
            dump_out = open(work / "goal.candump", "wb")  # noqa: SIM115 - closed below
            before = _can_receivers(candump)
            # line-buffered, so the file shows how far it has read (stopped below once it is quiet); a
            # 4 MiB socket buffer (-r; root may exceed rmem_max): with the default ~200 KiB a loaded
            # user-mode Linux dropped 5 of 700 ticks' frames before candump read them (make test, CI-like)
            dump = subprocess.Popen(["stdbuf", "-oL", "candump", "-L", "-r", str(4 << 20), candump], stdout=dump_out,
                                    stderr=subprocess.DEVNULL)
            _wait_for_receiver(candump, before, dump)  # bound before the sim sends its first frame
        t0 = time.monotonic()
        sim = procs.start("goal_sim", [BIN / "qnav-sim", "--map", "paper10", "--can", can, "--lockstep",
                                       "--duration", duration_s, "--start", START, "-q"])
        rob = procs.start("goal_robot", [BIN / "qnav-robot", "--can", can, "--lockstep", "--policy", CELL_POLICY,
                                         "--start", START, "--goal-cell", "9,0", "--duration", duration_s - 0.05,
                                         "--stats-json", stats, "--mavlink", "none"])
        res["sim_exit"], res["robot_exit"] = _wait(sim, 120), _wait(rob, 30)
        res["wall_s"] = round(time.monotonic() - t0, 2)
        if dump is not None:
            # a Ctrl-C drops what is still in its socket: stop it once its file has been still for
            # 2 s (a loaded user-mode Linux lags behind the sim)
            _wait_still(work / "goal.candump", still_s=2.0, timeout_s=30.0)
            stop_process(dump, timeout_s=5, sig=signal.SIGINT)
            dump_out.close()
            res["candump_lines"] = len((work / "goal.candump").read_text().splitlines())
        res["sim"] = _sim_summary(procs.log("goal_sim"))
        res["robot"] = _stats(stats)
        if res["sim_exit"] != 0 or res["robot_exit"] != 0:
            res["logs"] = {"sim": procs.log("goal_sim")[-1500:], "robot": procs.log("goal_robot")[-1500:]}
    return res


def estop(can: str, work: Path, *, sender: str = "bus", speed: float = 2.0, duration_s: float = 8.0) -> dict:
    """Paced drive; EStop from another node once DRIVING (`sender`: "bus" python-can, "cansend" can-utils).
    Paced as lockstep at most `speed` times real time (qnav-sim --max-speed): the e-stop arrives from
    another node at a wall-clock moment, while every tick is answered, so a slow or loaded machine
    (user-mode Linux with its twin beside it: robot tick p99 49 ms) slows the run instead of tripping
    the motor watchdog first (seen when it was paced at 4x)."""
    res: dict = {"scenario": "estop", "can": can, "sender": sender}
    tag = f"estop_{sender}"
    bus = open_bus(can)
    try:
        with _Procs(work) as procs:
            sim = procs.start(f"{tag}_sim", [BIN / "qnav-sim", "--map", "paper10", "--can", can, "--lockstep",
                                             "--max-speed", speed, "--duration", duration_s, "--start", START, "-q"])
            rob = procs.start(f"{tag}_robot", [BIN / "qnav-robot", "--can", can, "--lockstep", "--policy",
                                               CELL_POLICY, "--start", START, "--goal-cell", "9,0",
                                               "--exit-when-done", "--duration", duration_s - 0.1,
                                               "--mavlink", "none"])
            driving = False
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and not driving:
                msg = bus.recv(timeout=0.5)
                if msg is not None and cp.frame_name(msg.arbitration_id) == "ControllerHeartbeat":
                    driving = cp.decode(msg)[1]["Ctrl_State"] == CtrlState.DRIVING
            res["driving_seen"] = driving
            if driving:
                if sender == "cansend":
                    arg = estop_cansend_arg()
                    res["cansend"] = f"cansend {can.partition(':')[2]} {arg}"
                    r = subprocess.run(["cansend", can.partition(":")[2], arg], capture_output=True, text=True,
                                       check=False)
                    res["cansend_exit"] = r.returncode
                else:
                    bus.send(cp.encode("EStop", ESTOP_SIGNALS))
                zero = fault = False
                while time.monotonic() < deadline and not (zero and fault):
                    msg = bus.recv(timeout=0.5)
                    if msg is None:
                        continue
                    name = cp.frame_name(msg.arbitration_id)
                    if name == "MotorCommand":
                        sig = cp.decode(msg)[1]
                        zero = zero or (sig["Cmd_LeftSpeed"] == 0 and sig["Cmd_RightSpeed"] == 0)
                    elif name == "ControllerHeartbeat":
                        fault = fault or cp.decode(msg)[1]["Ctrl_State"] == CtrlState.FAULT
                res["zero_command_seen"], res["fault_heartbeat_seen"] = zero, fault
            res["robot_exit"] = _wait(rob, 30)
            # lockstep: with the robot gone the sim would wait out each remaining tick; Ctrl-C it
            res["sim_exit"] = stop_process(sim, timeout_s=10, sig=signal.SIGINT)
            log = procs.log(f"{tag}_robot")
            res["robot_fault_line"] = "FAULT: e-stop engaged" in log
            if res["robot_exit"] != 3 or not res["robot_fault_line"]:
                res["logs"] = {"robot": log[-1500:], "sim": procs.log(f"{tag}_sim")[-1500:]}
    finally:
        bus.shutdown()
    return res


CUT_FRAMES = ("RangeSectors0", "RangeSectors1", "EncoderCounts")


def sensor_stop(can: str, work: Path, *, timeout_ms: int = 250, t_cut_s: float = 2.0) -> dict:
    """This process is the plant (lockstep); at `t_cut_s` the range boards and encoders stop."""
    from firmware_py import robot_spec
    from ground_station.maps import load_map
    from sim_bridge.plant import Plant, SimConfig
    from sim_bridge.world import Pose

    period = robot_spec.CONTROL_PERIOD_US
    t_cut = round(t_cut_s * 1e6)
    cut_ids = {cp.FRAME_IDS[n] for n in CUT_FRAMES}
    stats = work / "sensor_robot.json"
    res: dict = {"scenario": "sensor_stop", "can": can, "cut": list(CUT_FRAMES), "timeout_ms": timeout_ms,
                 "t_cut_us": t_cut}
    plant = Plant(load_map("paper10").occ, SimConfig(seed=1), Pose(0.25, 0.25, 0.0))
    commands: list[tuple[int, int, int]] = []
    states: list[tuple[int, int]] = []
    bus = open_bus(can)
    try:
        with _Procs(work) as procs:
            rob = procs.start("sensor_robot", [BIN / "qnav-robot", "--can", can, "--lockstep", "--policy", CELL_POLICY,
                                               "--start", START, "--goal-cell", "9,0", "--sensor-timeout-ms",
                                               timeout_ms, "--exit-when-done", "--duration", 20, "--stats-json", stats,
                                               "--mavlink", "none"])
            started = False
            while plant.time_us < t_cut + timeout_ms * 1000 + 20 * period:
                frames = plant.tick_frames()
                if plant.time_us >= t_cut:
                    frames = [f for f in frames if f.arbitration_id not in cut_ids]
                for f in frames:
                    bus.send(f)
                answered = False
                deadline = time.monotonic() + (5.0 if started else 30.0)
                resend = time.monotonic() + 0.2
                while not answered and time.monotonic() < deadline:
                    msg = bus.recv(timeout=0.1)
                    if msg is None:
                        if not started and time.monotonic() > resend:  # a robot still starting up
                            bus.send(frames[-1])
                            resend = time.monotonic() + 0.2
                        continue
                    name = cp.frame_name(msg.arbitration_id)
                    if name == "MotorCommand":
                        sig = cp.decode(msg)[1]
                        if sig["Cmd_Counter"] == plant.tick % cp.TICK_MODULUS:
                            commands.append((plant.time_us, sig["Cmd_LeftSpeed"], sig["Cmd_RightSpeed"]))
                    elif name == "ControllerHeartbeat":
                        states.append((plant.time_us, cp.decode(msg)[1]["Ctrl_State"]))
                    answered = plant.handle(msg, lockstep=True) or answered
                if not answered:
                    break  # the robot ended (FAULT with --exit-when-done) or hangs
                started = True
                plant.step_period()
            res["robot_exit"] = _wait(rob, 30)
            res["robot"] = _stats(stats)
            res["robot_fault_line"] = "FAULT" in procs.log("sensor_robot")
            if res["robot_exit"] != 3:
                res["logs"] = {"robot": procs.log("sensor_robot")[-1500:]}
    finally:
        bus.shutdown()
    res["deadline_us"] = t_cut - period + timeout_ms * 1000 + period
    res["state_at_cut"] = next((CtrlState(s).name for t, s in reversed(states) if t < t_cut), None)
    zeros = [t for t, left, right in commands if t >= t_cut and left == 0 and right == 0]
    res["first_zero_us"] = zeros[0] if zeros else None
    res["nonzero_after_first_zero"] = sum(1 for t, left, right in commands
                                          if zeros and t >= zeros[0] and (left, right) != (0, 0))
    res["ticks_answered"] = len(commands)
    return res


def _qnav(procs: _Procs, name: str, args: list, timeout_s: float = 60) -> tuple[int | None, str]:
    p = procs.start(name, [BIN / "qnav", *args])
    return _wait(p, timeout_s), procs.log(name).strip()


def mission(can: str, work: Path, *, robot_mavlink: str | None = None, gcs_mavlink: str | None = None,
            robot_extra: list[str] | None = None, upload: Path | None = None, speed: float | None = None,
            max_speed: float | None = None, profile: str | None = None, targets: str = "A,B,C,D") -> dict:
    """Mission A-D over MAVLink, the ground side as `qnav` commands (module docstring).
    `profile`: a robot profile both programs run with (their drive and sensor backends).
    `targets`: the paper10 targets `qnav mission upload --targets` sends (A,B,C,D unless given).

    Default link: robot `udpout:127.0.0.1:P`, ground station `udpin:127.0.0.1:P`; a serial radio
    passes its two ends. `upload`: a policy file `qnav upload --activate`s first. `speed`: paced
    at that many times real time (robot on --sim-clock) instead of lockstep. `max_speed`: lockstep,
    but never faster than that many times real time: a real-time link such as a 57600-baud radio
    cannot carry telemetry sent on a clock running ~50x real time, and a loaded machine must only
    slow the run (paced, a stalled process trips the motor watchdog; lockstep answers every tick)."""
    if robot_mavlink is None or gcs_mavlink is None:
        port = free_udp_port()
        robot_mavlink, gcs_mavlink = f"udpout:127.0.0.1:{port}", f"udpin:127.0.0.1:{port}"
    res: dict = {"scenario": "mission", "can": can, "gcs": gcs_mavlink, "steps": {}, "profile": profile}
    n_targets = len(targets.split(","))
    prof = ["--profile", profile] if profile else []
    steps = res["steps"]
    link = ["--mavlink", gcs_mavlink]
    tlog = work / "mission.tlog"
    stats = work / "mission_robot.json"
    with _Procs(work) as procs:
        pace = ["--lockstep"] if speed is None else ["--speed", speed]
        if max_speed is not None:
            pace += ["--max-speed", max_speed]
        sim = procs.start("mission_sim", [BIN / "qnav-sim", "--map", "paper10", "--can", can, *pace,
                                          "--duration", 3000 if speed is None else 150 * speed, "--start", START,
                                          "-q", *prof])
        clock = "--lockstep" if speed is None else "--sim-clock"
        rob = procs.start("mission_robot", [BIN / "qnav-robot", "--can", can, clock, "--policy", CELL_POLICY,
                                            "--start", START, "--storage", work / "storage", "--duration", 2999.95,
                                            "--mavlink", robot_mavlink, "--stats-json", stats,
                                            # the ideal plant: exact odometry; the localiser's ~0.1 m corridor
                                            # error clipped the corner by B in some runs (docs/architecture.md)
                                            "--localiser", "off", *prof, *(robot_extra or [])])
        t0 = time.monotonic()
        if upload is not None:
            code, out = _qnav(procs, "qnav_upload", ["upload", upload, "--activate", *link,
                                                     "--timeout", "30"], 120)
            steps["upload"] = {"exit": code, "seconds": round(time.monotonic() - t0, 2), "out": out[-600:]}
        code, out = _qnav(procs, "qnav_mission", ["mission", "upload", "--targets", targets, "--map", "paper10", *link,
                                                  "--no-tlog", "--timeout", "30"])
        steps["mission_upload"] = {"exit": code, "out": out[-600:]}
        # lockstep runs the robot's clock ~50x real time: a ground station's 1 Hz wall-clock
        # heartbeat cannot hold its 5 s sim-time GCS failsafe, so the operator turns it off
        code, out = _qnav(procs, "qnav_param", ["param", "set", "FS_GCS_ENABLE", "0", *link, "--no-tlog",
                                                "--timeout", "30"])
        steps["param_fs_off"] = {"exit": code, "out": out[-600:]}
        deadline = time.monotonic() + 40
        tries = 0
        while True:  # arming waits for fresh sensor frames from the sim
            tries += 1
            code, out = _qnav(procs, f"qnav_arm{tries}", ["arm", *link, "--no-tlog", "--timeout", "20"])
            if code == 0 or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        steps["arm"] = {"exit": code, "tries": tries, "out": out[-600:]}
        # `qnav mode auto` starts the mission; the world is paused the moment it answers, until
        # the monitor listens (the robot's clock is the sim's: paused, it sends nothing)
        mode = procs.start("qnav_mode", [BIN / "qnav", "mode", "auto", *link, "--no-tlog", "--timeout", "20"])
        until = time.monotonic() + 30
        while exit_code(mode) is None and "mode auto" not in procs.log("qnav_mode") and time.monotonic() < until:
            time.sleep(0.005)
        if speed is None:  # paced, the sim's clock is the wall's: it would catch up in a burst
            sim.send_signal(signal.SIGSTOP)
        try:
            steps["mode_auto"] = {"exit": _wait(mode, 30), "out": procs.log("qnav_mode")[-600:]}
            mon = procs.start("qnav_monitor", [BIN / "qnav", "monitor", "--plain", *link, "--tlog", tlog])
            until = time.monotonic() + 20
            while time.monotonic() < until and exit_code(mon) is None and "recording to" not in procs.log("qnav_monitor"):
                time.sleep(0.05)
            time.sleep(0.3)
        finally:
            sim.send_signal(signal.SIGCONT)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and procs.log("mission_robot").count("-> GOAL_REACHED") < n_targets:
            if exit_code(rob) is not None or exit_code(sim) is not None:
                break
            time.sleep(0.2)
        # the last MISSION_ITEM_REACHED on its way: over a 57600-baud radio at 3x sim pacing the
        # telemetry queues for seconds behind the robot, so wait for the monitor to have it
        until = time.monotonic() + 30
        while time.monotonic() < until and f"reached={n_targets}" not in procs.log("qnav_monitor") \
                and exit_code(mon) is None:
            time.sleep(0.2)
        time.sleep(0.5)
        stop_process(mon, timeout_s=10, sig=signal.SIGINT)
        res["mission_wall_s"] = round(time.monotonic() - t0, 2)
        steps["monitor"] = {"exit": mon.returncode, "lines": len(procs.log("qnav_monitor").splitlines()),
                            "tail": procs.log("qnav_monitor")[-400:]}
        res["tlog"] = str(tlog)
        res["reached_seq"] = _reached_seq(tlog)
    res["robot"] = _stats(stats)
    res["robot_goal_reached_lines"] = procs.log("mission_robot").count("-> GOAL_REACHED")
    if res["reached_seq"] != list(range(n_targets)):
        res["logs"] = {"robot": procs.log("mission_robot")[-2000:], "sim": procs.log("mission_sim")[-800:]}
    return res


SECTOR_POLICY = "policies/sector.qtab"
REPLAN_START = "1.25,3.75,0"  # target A's cell (2, 2) of paper10, facing east
REPLAN_DISC = (3100.0, 4300.0, 150.0)  # in the open room north-east of A, across the plan to B: the policy stalls


def replan(can: str, work: Path, *, disc: tuple[float, float, float] = REPLAN_DISC,
           follow_timeout_s: float = 90.0) -> dict:
    """`qnav mission upload --targets B --plan --follow` with an unmapped disc across the plan.

    Lockstep sim on paper10 with the disc (`--scenario`), the robot on the shipped sector table
    without its local planner (a copy of the file without the `local_planner` metadata: the
    ground station's re-planning is for a robot that stalls; with the planner the robot goes round
    the disc itself) from A (`--localiser off`: the ideal plant's odometry is exact); the operator's commands as in
    `mission`, the follower in the background from before the robot is armed. The result has the
    follower's exit code and output, the robot's GOAL_REACHED lines and the sim's bumper contacts."""
    port = free_udp_port()
    link = ["--mavlink", f"udpin:127.0.0.1:{port}", "--no-tlog"]
    res: dict = {"scenario": "replan", "can": can, "disc": list(disc), "steps": {}}
    steps = res["steps"]
    scen = work / "scenario.json"
    scen.write_text(json.dumps({"discs": [list(disc)], "movers": []}))
    traj = work / "replan_trajectory.csv"
    policy = work / "sector_without_planner.qtab"
    shipped = load_policy(REPO / SECTOR_POLICY)
    policy.write_bytes(with_metadata(shipped, {k: v for k, v in shipped.metadata.items() if k != PLANNER_KEY}))
    with _Procs(work) as procs:
        sim = procs.start("replan_sim", [BIN / "qnav-sim", "--map", "paper10", "--can", can, "--lockstep",
                                         "--duration", 3000, "--start", REPLAN_START, "--scenario", scen,
                                         "--trajectory", traj, "-q"])
        rob = procs.start("replan_robot", [BIN / "qnav-robot", "--can", can, "--lockstep", "--policy", policy,
                                           "--start", REPLAN_START, "--storage", work / "storage",
                                           "--duration", 2999.95, "--mavlink", f"udpout:127.0.0.1:{port}",
                                           "--localiser", "off"])
        code, out = _qnav(procs, "replan_param", ["param", "set", "FS_GCS_ENABLE", "0", *link, "--timeout", "30"])
        steps["param_fs_off"] = {"exit": code, "out": out[-600:]}
        follow = procs.start("replan_follow", [BIN / "qnav", "mission", "upload", "--targets", "B", "--plan", "--map", "paper10",
                                               "--follow", "--follow-timeout", follow_timeout_s, "--mavlink", f"udpin:127.0.0.1:{port}", "--tlog", work / "follow.tlog",
                                               "--timeout", "30"])
        until = time.monotonic() + 30
        while time.monotonic() < until and exit_code(follow) is None and "following" not in procs.log("replan_follow"):
            time.sleep(0.05)
        deadline = time.monotonic() + 40
        tries = 0
        while True:  # arming waits for fresh sensor frames from the sim
            tries += 1
            code, out = _qnav(procs, f"replan_arm{tries}", ["arm", *link, "--timeout", "20"])
            if code == 0 or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        steps["arm"] = {"exit": code, "tries": tries, "out": out[-600:]}
        code, out = _qnav(procs, "replan_mode", ["mode", "auto", *link, "--timeout", "20"])
        steps["mode_auto"] = {"exit": code, "out": out[-600:]}
        res["follow_exit"] = _wait(follow, follow_timeout_s + 30)
        res["follow_out"] = procs.log("replan_follow")[-3000:]
        res["robot_goal_reached_lines"] = procs.log("replan_robot").count("-> GOAL_REACHED")
        res["robot_log_tail"] = procs.log("replan_robot")[-1500:]
        for p in (rob, sim):
            stop_process(p, timeout_s=10, sig=signal.SIGINT)
    res["bumper_contacts"] = _bumper_contacts(traj)
    return res


def _bumper_contacts(trajectory_csv: Path) -> int | None:
    """Bumper contact events in the sim's trajectory CSV (rows where contact starts); None without it."""
    from ground_station.demo import count_collisions

    try:
        return count_collisions(trajectory_csv)
    except (OSError, ValueError):
        return None


def _reached_seq(tlog: Path) -> list[int]:
    """MISSION_ITEM_REACHED seqs in a tlog, in order."""
    from ground_station.mavlink.link import mavutil

    if not tlog.exists():
        return []
    mlog = mavutil().mavlink_connection(str(tlog), dialect=DIALECT)
    seqs = []
    try:
        while (msg := mlog.recv_match(type="MISSION_ITEM_REACHED")) is not None:
            seqs.append(msg.seq)
    finally:
        mlog.close()
    return seqs


PROFILES = {"odrive": "firmware_py/profiles/odrive.toml", "dronecan": "firmware_py/profiles/dronecan.toml"}


def drive(can: str, work: Path, *, backend: str, fault: str | None = None, duration_s: float = 60.0) -> dict:
    """Lockstep drive to target B through the sim's boards for a drive backend (both programs with
    --profile firmware_py/profiles/BACKEND.toml); `fault` ("error" or "silent") hits the left axis
    or ESC at 3 s (an ODrive MOTOR_FAILED axis error, a DroneCAN ESC's health ERROR). 60 s: the
    profiles limit the wheels to 400 mm/s (the cell policy's moves run at up to 600 without one)."""
    tag = f"{backend}_{fault or 'goal'}"
    stats = work / f"{tag}_robot.json"
    res: dict = {"scenario": tag, "can": can, "fault": fault, "fault_at_s": 3.0 if fault else None}
    what = {"error": "error:0x40", "silent": "silent", None: None}[fault]
    inject = ["--drive-fault", f"3:{what}:left"] if what else []
    with _Procs(work) as procs:
        sim = procs.start(f"{tag}_sim", [BIN / "qnav-sim", "--map", "paper10", "--can", can, "--lockstep",
                                         "--duration", duration_s, "--start", START, "-q", "--profile",
                                         PROFILES[backend], *inject])
        rob = procs.start(f"{tag}_robot", [BIN / "qnav-robot", "--can", can, "--lockstep", "--policy", CELL_POLICY,
                                           "--start", START, "--goal-cell", "9,0", "--exit-when-done",
                                           "--duration", duration_s - 0.05, "--stats-json", stats,
                                           "--mavlink", "none", "--profile", PROFILES[backend]])
        res["robot_exit"] = _wait(rob, 120)
        # lockstep: with the robot gone the sim would wait out each remaining tick; Ctrl-C it
        res["sim_exit"] = stop_process(sim, timeout_s=10, sig=signal.SIGINT)
        res["robot"] = _stats(stats)
        res["sim"] = _sim_summary(procs.log(f"{tag}_sim"))
        if res["robot_exit"] != (3 if fault else 0):
            res["logs"] = {"sim": procs.log(f"{tag}_sim")[-1500:], "robot": procs.log(f"{tag}_robot")[-1500:]}
    return res


SCENARIOS: dict[str, Callable[..., dict]] = {
    **{f"{b}_{f or 'goal'}": functools.partial(drive, backend=b, fault=f)
       for b in PROFILES for f in (None, "error", "silent")},
    **{f"mission_{b}": functools.partial(mission, profile=PROFILES[b]) for b in PROFILES},
    "goal_reached": goal_reached,
    "estop": estop,
    "estop_cansend": lambda can, work: estop(can, work, sender="cansend"),
    "sensor_stop": sensor_stop,
    "mission": mission,
    "mission_ab": functools.partial(mission, targets="A,B"),  # the same sequence, two targets: half the drive
    "replan": replan,
}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Run HIL scenarios on one CAN transport; one JSON per scenario.")
    p.add_argument("--can", required=True, help="--can spec of the bus (e.g. socketcan:vcan0)")
    p.add_argument("--out", required=True, type=Path, help="directory for <scenario>.json, logs and work files")
    p.add_argument("--candump", metavar="CHANNEL", help="goal_reached: record the bus with candump -L CHANNEL")
    p.add_argument("names", nargs="+", choices=sorted(SCENARIOS), metavar="SCENARIO",
                   help=f"one or more of {', '.join(sorted(SCENARIOS))}")
    args = p.parse_args(argv)
    if args.candump and shutil.which("candump") is None:
        p.error("--candump needs candump (can-utils)")
    for name in args.names:
        work = args.out / name
        work.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        try:
            kw = {"candump": args.candump} if name == "goal_reached" and args.candump else {}
            res = SCENARIOS[name](args.can, work, **kw)
        except Exception as exc:  # noqa: BLE001 - reported to the test, which fails on it
            res = {"scenario": name, "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
        res["scenario_wall_s"] = round(time.monotonic() - t0, 2)
        (args.out / f"{name}.json").write_text(json.dumps(res, indent=1))
        print(f"{name}: {res.get('error', 'done')} ({res['scenario_wall_s']} s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
