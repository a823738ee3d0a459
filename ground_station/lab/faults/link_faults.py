"""MAVLink link faults: GCS link loss, a lossy radio, and load.

- `link_loss`: the MAVLink node core attached to the controller in the
  lockstep HIL rig, polled once per control tick as `qnav-robot` polls it;
  a ground station's heartbeats (seeded irregular spacing) feed it while the
  robot drives, then stop at a seeded moment. With a seeded FS_GCS_TOUT_MS
  and FS_GCS_ACTION (Hold or disarm), the failsafe transition must come
  after the timeout and no later than timeout + one control period after
  the last heartbeat (sim clock), with zero commands from the next tick on
  and a STATUSTEXT "GCS failsafe".
- `lossy_link`: `qnav-robot` (signing on) behind the link emulator
  (57600 baud, seeded loss with duplication and reordering) at each loss
  level: `qnav upload --activate`'s code puts a new policy version, and the
  ground station's commands (DO_SET_MODE, ARM) go through `Link.command`.
  An upload ends byte-exact, activated and confirmed, or with a one-line
  error; active.qtab on the robot is always a complete version and the
  robot runs it. A command is answered by a COMMAND_ACK (on the first try or
  a retry) or ends with a timeout error; an accepted mode shows in the
  robot's HEARTBEAT.
- `load`: `qnav-sim` paced in real time + `qnav-robot --sim-clock` on a
  python-can-remote hub, driving the paper10 tour, with three ground-station
  clients at once: a monitor-like client (heartbeats, all telemetry at
  10 Hz), a client asking for the parameter list and messages in a loop, and
  `qnav upload`'s code uploading policies back to back; with `floods`, a
  fourth client sends the floods of `ground_station.lab.faults.floods` in turn
  (600 PARAM_SET, 300 PARAM_REQUEST_LIST, 150 CalcFileCRC32 of a 6 MB file).
  No control tick may be missed on the sim clock (in the bench, none on the
  wall clock either); the
  robot's tick_p99_us / compute_p99_us are reported beside a baseline run
  without clients (the ratio is checked only by the bench, never a test).
"""

from __future__ import annotations

import random
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from ground_station.lab.faults.common import RobotProcess, ScenarioResult, register, trials

LOSS_LEVELS = (0.0, 0.05, 0.2, 0.4)


# --- link loss: GCS failsafe on the sim clock --------------------------------------------

def _from_gcs(make):
    """A message as the node receives it from a ground station: `make(m)` on
    pymavlink's common dialect, packed by the GCS and parsed back."""
    from ground_station.lab.faults.hostile_mav import _dialect
    from ground_station.mavlink.link import GCS_COMPID, GCS_SYSID

    m = _dialect()
    gcs = m.MAVLink(None, GCS_SYSID, GCS_COMPID)
    return m.MAVLink(None, 1, 1).parse_buffer(make(m).pack(gcs))[0]


def _gcs_heartbeat():
    return _from_gcs(lambda m: m.MAVLink_heartbeat_message(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))


def _param_set(name: str, value: int):
    return _from_gcs(lambda m: m.MAVLink_param_set_message(1, 1, name.encode(), float(value),
                                                           m.MAV_PARAM_TYPE_INT32))


@register("link_loss", small=4, large=20, unit="episodes",
          what="GCS heartbeats stop -> failsafe action within timeout + 1 control period (sim clock)")
def link_loss(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    from firmware_py.mavlink.node import MavNode
    from firmware_py.mavlink.params import ParamStore
    from firmware_py.mavlink.signing import Signing
    from firmware_py.vehicle import CtrlState
    from ground_station.lab.faults.can_faults import _drive_to
    from ground_station.lab.rigs.lockstep import (
        PERIOD_US,
        LockstepRig,
        cell_policy,
        far_trip,
        paper10,
    )

    hb = _gcs_heartbeat()
    gm, pol = paper10(), cell_policy()
    for i in trials(count, progress):
        rng = random.Random(seed * 7919 + 6000 + i)
        timeout_ms = rng.randrange(500, 3001, 10)
        action = 1 + i % 2  # Hold, disarm in turn
        start, goal = far_trip(gm, pol, rng, min_cells=8)
        rig = LockstepRig(gm.occ, pol, start, [goal], seed=rng.randrange(2**31))
        node = MavNode(rig.ctrl, ParamStore(None), Signing(None))
        node.boot(0)
        for name, value in (("FS_GCS_TOUT_MS", timeout_ms), ("FS_GCS_ACTION", action)):
            echo = node.handle(_param_set(name, value), 0)[-1]
            assert echo.param_value == value, (name, value, echo)
        t_stop = rng.randrange(20, 41) * PERIOD_US  # heartbeats stop 1-2 s in
        state: dict[str, Any] = {"next_hb": 0, "last_hb": None, "texts": []}

        def poll(_out, node=node, rng=rng, t_stop=t_stop, state=state, rig=rig, timeout_ms=timeout_ms):
            now = rig.node.clock.now_us()
            if now < t_stop and now >= state["next_hb"]:
                node.handle(hb, now)
                state["last_hb"] = now
                # irregular, but never longer than the timeout (that would be a real outage)
                state["next_hb"] = now + rng.randrange(100_000, min(1_000_000, timeout_ms * 1000 - PERIOD_US),
                                                       PERIOD_US)
            for msg in node.tick(now):
                if msg.get_type() == "STATUSTEXT":
                    state["texts"].append((now, msg.text))

        rig.node.after_tick.append(poll)
        problems: list[str] = []
        with rig:
            _drive_to(rig, t_stop, "when heartbeats stop", problems)
            last_hb = state["last_hb"]
            deadline = last_hb + timeout_ms * 1000 + PERIOD_US
            rig.run_until(deadline + 4 * PERIOD_US)
        want = CtrlState.HOLD if action == 1 else CtrlState.STANDBY
        tr = next((t for t in rig.ctrl.transitions if t.t_us > last_hb and t.dst == want), None)
        if tr is None or tr.t_us > deadline:
            problems.append(f"no {want.name} by {deadline} us ({tr})")
        elif tr.t_us <= last_hb + timeout_ms * 1000:
            problems.append(f"failsafe at {tr.t_us} us, before the timeout ran out")
        else:
            late = [c for c in rig.commands if c[0] > tr.t_us and (c[1] or c[2])]
            if late:
                problems.append(f"non-zero command {late[0]} after the failsafe")
            if not any("GCS failsafe" in text for t, text in state["texts"] if t >= tr.t_us):
                problems.append("no STATUSTEXT 'GCS failsafe'")
        res.check(problems, f"seed {seed}/{i} timeout {timeout_ms} ms action {want.name}")


# --- lossy radio: uploads and commands through the link emulator -------------------------

def _emulator():
    from ground_station.lab.rigs import link_emulator

    return link_emulator


class _CountingLink:
    """Counts COMMAND_LONGs a `ground_station.mavlink.link.Link` sends (its retries)."""

    def __init__(self, link) -> None:
        self.sent = 0
        orig = link.conn.mav.command_long_send

        def counting(*a, **k):
            self.sent += 1
            return orig(*a, **k)

        link.conn.mav.command_long_send = counting


def lossy_trial(loss: float, seed: int, tmp: Path, *, deadline_s: float, commands: int = 4) -> dict:
    # a session: robot process + emulator; the upload, then the commands, then what the robot runs
    """One robot behind the emulator at `loss`: one upload + activation, `commands` commands."""
    from firmware_py.policy import load_policy
    from firmware_py.storage import ACTIVE_POLICY, Storage
    from ground_station.lab.faults.crash import policy_version
    from ground_station.lab.rigs.lockstep import CELL_POLICY
    from ground_station.mavlink.ftp_upload import ftp_session, upload_policy
    from ground_station.mavlink.link import Link, LinkError, mavlink

    emu = _emulator()
    rng = random.Random(seed)
    storage_dir = tmp / f"robot-{seed}"
    base = CELL_POLICY.read_bytes()
    Storage(storage_dir).write_atomic(ACTIVE_POLICY, base)
    new = policy_version(CELL_POLICY, 0x10550000 + seed)
    local = tmp / f"lossy-{seed}.qtab"
    local.write_bytes(new)
    key_file = tmp / f"link-{seed}.key"  # per trial: trials may run side by side in one directory
    key_file.write_text(random.Random(seed).randbytes(32).hex())
    row: dict = {"loss": loss, "seed": seed, "problems": []}
    problems = row["problems"]
    cfg = emu.LinkConfig(loss=loss, duplicate=min(0.1, loss / 2), reorder=min(0.1, loss / 2),
                         reorder_delay_s=0.03, seed=seed)
    robot = RobotProcess(storage_dir, key_file=key_file, log=tmp / f"robot-{seed}.log")
    with robot, emu.LinkEmulator(cfg, robot_peer=("127.0.0.1", robot.port)) as link:
        url = f"udpout:127.0.0.1:{link.gcs_port}"
        # upload + activation with qnav upload's own code
        t0 = time.monotonic()
        gcs = Link(url, signing_key=key_file, tlog=False)
        try:
            gcs.connect(30.0)
        except LinkError as exc:
            gcs.close()
            problems.append(f"setup: {exc}")
            return row
        try:
            res = upload_policy(gcs, local, f"/policies/{local.name}", activate=True, deadline_s=deadline_s,
                                attempts=8)
            row.update(upload="ok", upload_s=time.monotonic() - t0, puts=res.put_attempts, renames=res.renames,
                       confirmed_by=res.confirmed_by)
        except LinkError as exc:
            text = str(exc)
            row.update(upload="failed", upload_s=time.monotonic() - t0, error=text, exit=exc.code)
            if not text or "\n" in text or exc.code not in (3, 4, 5):
                problems.append(f"unclear upload error (exit {exc.code}): {text!r}")
        finally:
            puts = ftp_session(gcs).puts
            row["writes"] = {"sent": sum(p.writes_sent for p in puts), "blocks": sum(p.blocks for p in puts)}
            gcs.close()
        t_cmd = time.monotonic()
        # commands through the shared link layer, with its retries
        m = mavlink()
        glink = Link(url, signing_key=key_file, tlog=False)
        counter = _CountingLink(glink)
        acked = retried = timed_out = 0
        try:
            glink.connect(30.0)
            for k in range(commands):
                mode = (4, 15)[k % 2] if rng.random() < 0.75 else None
                before = counter.sent
                try:
                    if mode is None:  # ARM: the robot has no sensors here, so DENIED is its answer
                        r = glink.command(m.MAV_CMD_COMPONENT_ARM_DISARM, 1, check=False)
                        if r.result != m.MAV_RESULT_DENIED:
                            problems.append(f"ARM answered {r.result}, expected DENIED")
                    else:
                        glink.command(m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)
                        hb = glink.recv("HEARTBEAT", 10.0, cond=lambda h, mode=mode: h.custom_mode == mode)
                        if hb is None:
                            problems.append(f"mode {mode} ACKed but never in HEARTBEAT")
                    acked += 1
                    retried += counter.sent - before > 1
                except LinkError as exc:
                    timed_out += 1
                    if exc.code != 4 or "no COMMAND_ACK" not in str(exc):
                        problems.append(f"command error not a clear timeout: {exc}")
            # what the robot runs now, asked over the same lossy link
            reported: dict[str, float | None] = {}
            for name in ("POLICY_CRC_HI", "POLICY_CRC_LO"):
                try:
                    reported[name] = glink.param_get(name, timeout_s=1.0, retries=10)
                except LinkError:
                    reported[name] = None
        except LinkError as exc:
            problems.append(f"setup: {exc}")
            reported = {}
        finally:
            glink.close()
        row.update(commands=commands, acked=acked, acked_after_retry=retried, timed_out=timed_out,
                   commands_s=time.monotonic() - t_cmd,
                   link_up=vars(link.stats.up).copy(), link_down=vars(link.stats.down).copy())
    # the robot's storage: a complete version, and the one it ran; the verdict says what happened
    active = Storage(storage_dir).resolve(ACTIVE_POLICY).read_bytes()
    if active not in (base, new):
        problems.append(f"active.qtab is neither the old nor the new version ({len(active)} B)")
    elif row.get("upload") == "ok" and active != new:
        problems.append("upload reported done but active.qtab is the old version")
    elif row.get("exit") in (3, 5) and active == new:
        # a refusal or a mismatch is a statement about the robot; a timeout only says "not confirmed"
        problems.append(f"upload said exit {row['exit']} ({row['error']}) but the robot activated the file")
    row["unconfirmed_but_active"] = row.get("exit") == 4 and active == new
    crc = load_policy(active).crc if active in (base, new) else None
    if (crc is not None and reported and None not in reported.values()
            and (reported["POLICY_CRC_HI"], reported["POLICY_CRC_LO"]) != (crc >> 16, crc & 0xFFFF)):
        problems.append("the robot runs a policy other than active.qtab")
    row["byte_exact"] = active == new
    return row


@register("lossy_link", small=2, large=12, unit="uploads+commands sessions (0/5/20/40 % loss)",
          what="lossy radio: upload byte-exact+activated or clear error; commands ACKed or timed out")
def lossy_link(res: ScenarioResult, count: int, seed: int, progress: Any, deadline_s: float = 120.0,
               levels: tuple[float, ...] = LOSS_LEVELS, commands: int = 4, workers: int = 1) -> None:
    """Trial i runs at loss levels[i % len(levels)] with seed seed * 1000 + i (robot key,
    link RNGs, policy version). `workers` > 1 runs trials side by side: each has its own
    robot process, emulator, storage and sockets, and mostly waits on its 57600 link."""
    from concurrent.futures import ThreadPoolExecutor

    _emulator()  # loaded once here, not by two trials at the same moment
    with tempfile.TemporaryDirectory(prefix="qnav-lossy-") as tmp:
        def trial(i: int) -> dict:
            row = lossy_trial(levels[i % len(levels)], seed * 1000 + i, Path(tmp), deadline_s=deadline_s,
                              commands=commands)
            if progress is not None:
                progress.update(1)
            return row

        with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
            rows = list(pool.map(trial, range(count)))
    for row in rows:
        res.check(row["problems"], f"loss {row['loss']:.0%} seed {row['seed']}")
    per_loss = {}
    for loss in levels:
        rs = [r for r in rows if r["loss"] == loss]
        if rs:
            per_loss[f"{loss:.0%}"] = {
                "sessions": len(rs), "uploads_ok": sum(r.get("upload") == "ok" for r in rs),
                "uploads_failed_clearly": sum(r.get("upload") == "failed" for r in rs),
                "commands": sum(r.get("commands", 0) for r in rs), "acked": sum(r.get("acked", 0) for r in rs),
                "acked_after_retry": sum(r.get("acked_after_retry", 0) for r in rs),
                "timed_out": sum(r.get("timed_out", 0) for r in rs),
                "unconfirmed_but_active": sum(r.get("unconfirmed_but_active", False) for r in rs),
                "max_upload_s": max((r.get("upload_s", 0.0) for r in rs), default=0.0)}
    res.figures.update({"per_loss": per_loss, "sessions": rows})


# --- load: three ground stations, 10 Hz telemetry, an upload, while driving ---------------

class _Client(threading.Thread):
    """One ground-station client doing `work(link)` until stopped; errors are kept."""

    def __init__(self, name: str, work, stop: threading.Event) -> None:
        super().__init__(name=name, daemon=True)
        self.work, self.stop_event = work, stop
        self.error = ""
        self.counts: dict[str, float] = {}  # message counts, plus t0/t1 (monotonic s)

    def run(self) -> None:
        try:
            self.work(self)
        except Exception as exc:
            if not self.stop_event.is_set():
                self.error = f"{type(exc).__name__}: {exc}"


TELEMETRY_10HZ = ("LOCAL_POSITION_NED", "ATTITUDE", "GLOBAL_POSITION_INT", "NAV_CONTROLLER_OUTPUT",
                  "OBSTACLE_DISTANCE")


LOAD_KEYS = ("ticks", "sim_ticks", "overruns", "can_errors", "tick_p50_us", "tick_p99_us", "tick_max_us",
             "compute_p50_us", "compute_p99_us", "compute_max_us", "lag_p99_us", "lag_max_us", "wall_overruns",
             "wall_late_ticks", "period_us", "cpu_percent", "rss_mb", "state", "link_polls", "link_frames",
             "link_budget_exhausted", "link_poll_max_ms", "link_handler_errors", "storage_saves",
             "storage_coalesced", "switch_interval_us")


def load_run(duration_s: float, seed: int, tmp: Path, clients_on: bool = True, floods: bool = False,
             extra_args: tuple[str, ...] = (), wall_strict: bool = False) -> dict:
    """One paced real-time HIL run across processes under MAVLink load; the robot's stats.
    `clients_on=False` is the baseline: the same run (same robot, storage and
    MAVLink node) with no ground station at all; `floods` adds the flood client.
    `wall_strict`: control periods lost on the wall clock are a problem too
    (the bench; see ground_station.lab.faults.floods for why tests leave it off)."""
    import json
    import subprocess

    from firmware_py import robot_spec as rb
    from firmware_py.storage import ACTIVE_POLICY, Storage
    from ground_station.canhub import CanHub
    from ground_station.lab.faults import floods as flood_mod
    from ground_station.lab.faults.crash import policy_version
    from ground_station.lab.rigs.lockstep import CELL_POLICY, paper10
    from ground_station.mavlink.ftp_upload import upload_policy
    from ground_station.mavlink.link import Link
    from ground_station.processes import ChildProcess, qnav_sim

    gm = paper10()
    storage_dir = tmp / f"robot-{seed}"
    Storage(storage_dir).write_atomic(ACTIVE_POLICY, CELL_POLICY.read_bytes())
    (storage_dir / flood_mod.BIG_FILE).write_bytes(random.Random(seed).randbytes(flood_mod.BIG_BYTES))
    stats_file = tmp / f"load-{seed}.json"
    x, y = rb.cell_center_mm(0, 9, gm.height)
    tour = [gm.targets[t] for t in ("A", "B", "D", "C")]
    stop, ready = threading.Event(), threading.Event()
    out: dict = {"duration_s": duration_s, "problems": []}
    with CanHub(f"load{seed}") as hub:
        sim = ChildProcess(qnav_sim("--map", "paper10", "--can", hub.spec, "--realtime", "--duration",
                                    str(duration_s + 30), "--start", f"{x / 1000},{y / 1000},90", "-q"), None)
        sim.start()
        extra = ["--sim-clock", "--start-cell", "0,9,90", "--duration", str(duration_s),
                 "--stats-json", str(stats_file), "-q", *extra_args]
        for c, r in tour:
            extra += ["--goal-cell", f"{c},{r}"]
        robot = RobotProcess(storage_dir, can=hub.spec, extra=extra, log=tmp / f"load-{seed}.log")
        clients: list[_Client] = []
        try:
            robot.start()

            def monitor(cl: _Client) -> None:  # heartbeats, all telemetry at 10 Hz
                link = Link(robot.url, tlog=False, heartbeat=True)
                try:
                    link.connect(30.0)
                    for name in ("TELEM_POS_HZ", "TELEM_NAV_HZ"):
                        link.param_set(name, 10)
                    ready.set()  # the others start now: their PARAM_VALUEs would confuse the echo
                    cl.counts["t0"] = time.monotonic()
                    while not stop.is_set():
                        msg = link.conn.recv_match(blocking=True, timeout=0.1)
                        if msg is not None:
                            cl.counts[msg.get_type()] = cl.counts.get(msg.get_type(), 0) + 1
                    cl.counts["t1"] = time.monotonic()
                finally:
                    link.close()

            def asker(cl: _Client) -> None:  # parameter lists and message requests in a loop
                link = Link(robot.url, tlog=False)
                m = link.m
                try:
                    link.connect(30.0)
                    while not stop.is_set():
                        link.param_list()
                        cl.counts["param_lists"] = cl.counts.get("param_lists", 0) + 1
                        link.command(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_SYS_STATUS)
                        cl.counts["requests"] = cl.counts.get("requests", 0) + 1
                finally:
                    link.close()

            def uploader(cl: _Client) -> None:  # uploads back to back (no activation: it is driving)
                # 15 s each: well over a 2.2 KB put on loopback, and the thread ends soon after the
                # robot does (its requests then go unanswered until the deadline)
                link = Link(robot.url, tlog=False)
                try:
                    link.connect(30.0)
                    k = 0
                    while not stop.is_set():
                        k += 1
                        local = tmp / f"load-{seed}-{k}.qtab"
                        local.write_bytes(policy_version(CELL_POLICY, 0x10AD0000 + k))
                        upload_policy(link, local, f"/policies/{local.name}", deadline_s=15, attempts=3)
                        cl.counts["uploads"] = k
                finally:
                    link.close()

            def flooder(cl: _Client) -> None:  # the floods in turn, each followed by its catch-up second
                link = Link(robot.url, tlog=False)
                try:
                    link.connect(30.0)
                    k = 0
                    while not stop.is_set():
                        kind = flood_mod.FLOOD_KINDS[k % len(flood_mod.FLOOD_KINDS)]
                        flood_mod.flood(link, kind, flood_mod.FLOOD_COUNTS[kind])
                        k += 1
                        cl.counts[kind] = cl.counts.get(kind, 0) + 1
                finally:
                    link.close()

            work = [("monitor", monitor), ("asker", asker), ("uploader", uploader)]
            if floods:
                work.append(("flooder", flooder))
            clients = [_Client(n, w, stop) for n, w in work] if clients_on else []
            if clients_on:
                clients[0].start()
            if clients_on and not ready.wait(60.0):
                out["problems"].append(f"monitor client not ready: {clients[0].error}")
            for cl in clients[1:]:
                cl.start()
            # the robot ends itself after `duration_s` of sim time (--duration)
            robot.wait(duration_s + 60)
        except subprocess.TimeoutExpired:
            out["problems"].append("qnav-robot did not end after its duration")
        finally:
            stop.set()
            for cl in clients:
                cl.join(timeout=30)
            robot.stop()
            sim.stop(grace_s=10)
    if robot.returncode not in (0, 4):  # 4: the tour was still going at the end
        out["problems"].append(f"qnav-robot exit {robot.returncode}: {robot.log_tail()}")
    for cl in clients:
        if cl.error:
            out["problems"].append(f"client {cl.name}: {cl.error}")
    try:
        st = json.loads(stats_file.read_text())
    except (OSError, ValueError) as exc:
        out["problems"].append(f"no robot stats: {exc}")
        return out
    mon = clients[0].counts if clients else {}
    span = mon.get("t1", 0) - mon.get("t0", 0)
    out.update({k: st[k] for k in LOAD_KEYS if k in st})
    if floods and len(clients) > 3:
        out["floods_done"] = {k: v for k, v in clients[3].counts.items() if k in flood_mod.FLOOD_COUNTS}
    out["telemetry_hz"] = {t: mon.get(t, 0) / span for t in TELEMETRY_10HZ} if span > 0 else {}
    out["uploads"] = clients[2].counts.get("uploads", 0) if clients else 0
    out["param_lists"] = clients[1].counts.get("param_lists", 0) if clients else 0
    out["transitions"] = st.get("transitions", [])
    if st["overruns"]:
        out["problems"].append(f"{st['overruns']} control ticks missed")
    if wall_strict and st.get("wall_overruns"):
        out["problems"].append(f"{st['wall_overruns']} control periods lost on the wall clock "
                               f"(lag max {st.get('lag_max_us', 0):.0f} us)")
    if st["ticks"] != st["sim_ticks"] or st["ticks"] < duration_s * 20 * 0.5:
        out["problems"].append(f"{st['ticks']} control ticks for {st['sim_ticks']} sim ticks")
    if st["state"] == "FAULT":
        out["problems"].append(f"robot in FAULT: {st.get('fault')}")
    if not any(t[2] == "DRIVING" for t in out["transitions"]):
        out["problems"].append("the robot never drove")
    if clients_on and not (out["uploads"] and out["param_lists"]):
        out["problems"].append("setup: the clients did not get their work done")
    return out


@register("load", small=1, large=3, unit="runs of 8 s (test) / 30 s (bench) sim time at real time",
          what="3 GCS clients + 10 Hz telemetry + uploads (+ floods in the bench) while driving: no missed tick")
def load(res: ScenarioResult, count: int, seed: int, progress: Any, duration_s: float | None = None,
         baseline: bool = False, floods: bool | None = None) -> None:
    """`baseline`: first one run without clients, reported beside (the bench's ratio).
    `floods` (default: with the baseline, i.e. in the bench) adds the flood client."""
    if floods is None:
        floods = baseline
    if duration_s is None:
        duration_s = 8.0 if count <= 1 else 30.0
    runs = []
    with tempfile.TemporaryDirectory(prefix="qnav-load-") as tmp:
        if baseline:
            base = load_run(duration_s, seed * 1000 + 999, Path(tmp), clients_on=False)
            res.figures["baseline"] = {k: v for k, v in base.items() if k != "transitions"}
        for i in trials(count, progress):
            run = load_run(duration_s, seed * 1000 + i, Path(tmp), floods=floods, wall_strict=baseline)
            runs.append({k: v for k, v in run.items() if k != "transitions"})
            res.check(run["problems"], f"run {i}")
    res.figures["runs"] = runs
    p99 = [r["tick_p99_us"] for r in runs if "tick_p99_us" in r]
    if p99:
        res.figures["tick_p99_us_max"] = max(p99)
        res.figures["tick_max_us_max"] = max(r["tick_max_us"] for r in runs if "tick_max_us" in r)
        res.figures["compute_p99_us_max"] = max(r.get("compute_p99_us", 0.0) for r in runs)
