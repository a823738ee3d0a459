"""Link floods and garbage while driving (issue 13): the control loop must not notice.

Both scenarios run the real processes in paced HIL: a python-can-remote hub,
`qnav-sim --realtime` and `qnav-robot --sim-clock` (MAVLink on UDP loopback,
storage with a large file in it) driving the paper10 tour A, B, D, C.

- `floods`: one ground station (heartbeats at 4 Hz) sends, one after the
  other, 600 PARAM_SET (a setting that changes every time, so each is a
  save), 300 PARAM_REQUEST_LIST (~13 000 PARAM_VALUEs to send) and 150
  MAVLink FTP CalcFileCRC32 of a 6 MB file, each at up to 1000 frames/s. A
  flood (one trial) holds when, after it, the robot still answers a
  PARAM_REQUEST_READ and its HEARTBEAT does not say FAULT (MAV_STATE_CRITICAL /
  EMERGENCY). At the end of the run (one more trial): no FAULT transition
  (a tick held up longer than MOT_TIMEOUT_MS trips the sim's motor-driver
  watchdog, paced in real time), every SimTick stepped (ticks == sim_ticks,
  no sim-time overrun), and the robot drove. Control periods lost on the
  wall clock (SYS_STATUS errors_count2 around each flood, `wall_overruns`
  at the end) are always measured; with `wall_strict` (the bench) they
  count as lost trials too. Tests leave it off: on a shared two-core
  machine the lag also holds the sim's and the hub's own lateness, which
  the robot cannot tell from its own.
- `failsafe_garbage`: FS_GCS_TOUT_MS=1000, FS_GCS_ACTION=Hold; while the
  robot drives, a second sender (another system id) floods malformed input:
  NaN/inf MISSION_ITEMs inside a mission upload, NaN goals, NaN PARAM_SETs
  and COMMAND_LONGs, random bytes, truncated frames and frames with a broken
  CRC; then the ground station's heartbeats stop while the garbage goes on.
  The robot must go to HOLD with cause "GCS failsafe" after FS_GCS_TOUT_MS
  and no later than FS_GCS_TOUT_MS + one control period after the last
  heartbeat it recorded (robot time: `gcs_last_heartbeat_us` in its
  --stats-json), and keep ticking (no missed tick, no FAULT). Exceptions the
  handlers raised are reported (`link_handler_errors`), not asserted: the
  shell must survive them either way.
"""

from __future__ import annotations

import json
import math
import random
import struct
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

from firmware_py.mavlink.dialect import NAME as DIALECT
from ground_station.lab.faults.common import RobotProcess, ScenarioResult, register, trials

FLOOD_COUNTS = {"param_set": 600, "param_list": 300, "crc": 150}
FLOOD_KINDS = tuple(FLOOD_COUNTS)
BIG_FILE = "policies/big.bin"  # in the robot's storage; FTP path /policies/big.bin
BIG_BYTES = 6 * 1024 * 1024
FLOOD_RATE_HZ = 1000.0
TOUR = ("A", "B", "D", "C")
FS_TIMEOUT_MS = 1000
MAV_STATE_CRITICAL, MAV_STATE_EMERGENCY = 5, 6


@contextmanager
def driving_robot(tmp: Path, seed: int, duration_s: float, *, big_file: bool = False,
                  extra: tuple[str, ...] = ()) -> Iterator[dict[str, Any]]:
    """Hub + qnav-sim --realtime + qnav-robot --sim-clock on the paper10 tour.
    Yields a dict with `robot` (RobotProcess); after the block it holds the
    robot's --stats-json as `stats` (or `problems`)."""
    from firmware_py import robot_spec as rb
    from firmware_py.storage import ACTIVE_POLICY, Storage
    from ground_station.canhub import CanHub
    from ground_station.lab.rigs.lockstep import CELL_POLICY, paper10
    from ground_station.processes import ChildProcess, qnav_sim

    gm = paper10()
    storage_dir = tmp / f"robot-{seed}"
    Storage(storage_dir).write_atomic(ACTIVE_POLICY, CELL_POLICY.read_bytes())
    if big_file:
        (storage_dir / BIG_FILE).write_bytes(random.Random(seed).randbytes(BIG_BYTES))
    stats_file = tmp / f"stats-{seed}.json"
    x, y = rb.cell_center_mm(0, 9, gm.height)
    args = ["--sim-clock", "--start-cell", "0,9,90", "--duration", str(duration_s), "--stats-json",
            str(stats_file), "-q", *extra]
    for c, r in (gm.targets[t] for t in TOUR):
        args += ["--goal-cell", f"{c},{r}"]
    ctx: dict[str, Any] = {"problems": []}
    with CanHub(f"flood{seed}") as hub:
        sim = ChildProcess(qnav_sim("--map", "paper10", "--can", hub.spec, "--realtime", "--duration",
                                    str(duration_s + 30), "--start", f"{x / 1000},{y / 1000},90", "-q"), None)
        robot = RobotProcess(storage_dir, can=hub.spec, extra=args, log=tmp / f"robot-{seed}.log")
        ctx["robot"] = robot
        sim.start()
        try:
            robot.start()
            yield ctx
            # the scenario is done: Ctrl-C (a clean exit writes the stats). Not waiting out the
            # duration, which is only a cap: a busy machine made the floods outlast a duration sized
            # for a quiet one, and the robot had ended before the last flood ("no HEARTBEAT after it")
            if not robot.alive:
                ctx["problems"].append(f"qnav-robot ended before the scenario did (exit {robot.returncode}; "
                                       f"duration cap {duration_s:g} s): {robot.log_tail()}")
        finally:
            code = robot.stop()
            if code not in (0, 130):
                ctx["problems"].append(f"qnav-robot exit {code} on Ctrl-C: {robot.log_tail()}")
            sim.stop(grace_s=10)
    try:
        ctx["stats"] = json.loads(stats_file.read_text())
    except (OSError, ValueError) as exc:
        ctx["problems"].append(f"no robot stats: {exc}; {robot.log_tail()}")


def run_problems(st: dict[str, Any], wall_strict: bool = False) -> list[str]:
    """End-of-run invariants from the robot's stats: every tick, no FAULT, it drove
    (with `wall_strict`, no control period lost on the wall clock)."""
    out = []
    trans = st.get("transitions", [])
    faults = [t for t in trans if t[2] == "FAULT"]
    if faults:
        out.append(f"FAULT at {faults[0][0]} us: {faults[0][3]}")
    if st["overruns"] or st["ticks"] != st["sim_ticks"]:
        out.append(f"missed ticks: {st['ticks']} steps for {st['sim_ticks']} SimTicks, {st['overruns']} overruns")
    if wall_strict and st.get("wall_overruns", 0):
        out.append(f"{st['wall_overruns']} control periods lost on the wall clock (lag max {st['lag_max_us']:.0f} us)")
    if not any(t[2] == "DRIVING" for t in trans):
        out.append("the robot never drove")
    return out


def _wait_armed(link: Any, timeout_s: float, beat: threading.Event) -> bool:
    """Until the robot's HEARTBEAT says armed (heartbeats go on in the background)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        hb = link.recv("HEARTBEAT", 0.5)
        if hb is not None and hb.base_mode & link.m.MAV_MODE_FLAG_SAFETY_ARMED:
            return True
    return False


def _as_operator(url: str, problems: list[str], body: Callable[..., None], *args: Any,
                 params: tuple[tuple[str, int], ...] = ()) -> None:
    """`body(link, beats, *args)` with the operator's `Link` to the robot at `url` connected,
    beating (`beats`, a `_Heartbeats` the body may stop), `params` set and the robot armed, else a
    setup problem in `problems`, as is a LinkError out of the body; the heartbeats stop and the
    link closes after."""
    from ground_station.mavlink.link import Link, LinkError

    link = Link(url, tlog=False)
    beats: _Heartbeats | None = None
    try:
        link.connect(30.0)
        beats = _Heartbeats(link)  # first: a short failsafe timeout must not run out during the setup
        beats.start()
        for name, value in params:
            link.param_set(name, value)
        if not _wait_armed(link, 20.0, beats.stop):
            problems.append("setup: the robot did not arm")
        body(link, beats, *args)
    except LinkError as exc:
        problems.append(f"setup: {exc}")
    finally:
        if beats is not None:
            beats.stop.set()
            beats.join(2)
        link.close()


class _Heartbeats(threading.Thread):
    """A ground station's heartbeats at 4 Hz until `stop` is set."""

    def __init__(self, link: Any) -> None:
        super().__init__(name="gcs-heartbeats", daemon=True)
        self.link = link
        self.stop = threading.Event()
        self.last_sent = 0.0

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                self.link.send_heartbeat()
                self.last_sent = time.monotonic()
            except OSError:
                pass
            self.stop.wait(0.25)


def _ftp(m: Any, seq: int, opcode: int, data: bytes) -> list[int]:
    hdr = struct.pack("<HBBBBBBI", seq & 0xFFFF, 0, opcode, len(data), 0, 0, 0, 0)
    return list((hdr + data).ljust(251, b"\0"))


def _drain(link: Any) -> int:
    n = 0
    while link.conn.recv_match(blocking=False) is not None:
        n += 1
    return n


def flood(link: Any, kind: str, count: int, rate_hz: float = FLOOD_RATE_HZ) -> dict[str, Any]:
    """Send `count` frames of `kind` at up to `rate_hz`; count what came back."""
    mav, sysid, compid = link.conn.mav, link.sysid, link.compid
    replies = 0
    t0 = time.monotonic()
    for i in range(count):
        if kind == "param_set":
            mav.param_set_send(sysid, compid, b"MIS_RETRIES", float(3 + i % 2), link.m.MAV_PARAM_TYPE_INT32)
        elif kind == "param_list":
            mav.param_request_list_send(sysid, compid)
        else:
            mav.file_transfer_protocol_send(0, sysid, compid, _ftp(link.m, i, 14, f"/{BIG_FILE}".encode()))
        if i % 10 == 9:
            replies += _drain(link)
            time.sleep(max(0.0, t0 + (i + 1) / rate_hz - time.monotonic()))
    sent_s = time.monotonic() - t0
    t_end = time.monotonic() + 1.0  # let the robot catch up, keep reading its answers
    while time.monotonic() < t_end:
        replies += _drain(link)
        time.sleep(0.01)
    return {"kind": kind, "sent": count, "send_s": round(sent_s, 3), "replies": replies}


def _sys_status(link: Any) -> Any:
    return link.recv("SYS_STATUS", 3.0)


@register("floods", small=3, large=9, unit="floods (600 PARAM_SET / 300 PARAM_REQUEST_LIST / 150 CRC32 of 6 MB)",
          what="MAVLink floods while driving in paced HIL: no FAULT, no missed tick, robot answers")
def floods(res: ScenarioResult, count: int, seed: int, progress: Any, duration_s: float | None = None,
           counts: dict[str, int] | None = None, wall_strict: bool = False) -> None:
    """Flood i is FLOOD_KINDS[i % 3]; all of them in one robot run, plus one
    end-of-run trial on the robot's stats."""
    from ground_station.mavlink.link import LinkError

    counts = counts or FLOOD_COUNTS
    kinds = [FLOOD_KINDS[i % len(FLOOD_KINDS)] for i in range(count)]
    if duration_s is None:  # a cap (the run ends with the floods): 4-5 s a flood on a busy machine
        duration_s = 60.0 + 15.0 * count
    rows: list[dict[str, Any]] = []

    def each_flood(link: Any, _beats: _Heartbeats) -> None:
        for kind in kinds:
            st0 = _sys_status(link)
            row = flood(link, kind, counts[kind])
            problems = []
            hb = link.recv("HEARTBEAT", 2.0)
            if hb is None:
                problems.append("no HEARTBEAT after the flood")
            elif hb.system_status in (MAV_STATE_CRITICAL, MAV_STATE_EMERGENCY):
                problems.append(f"robot HEARTBEAT system_status {hb.system_status} (FAULT)")
            try:
                link.param_get("SYSID_THISMAV", timeout_s=1.0, retries=5)
            except LinkError as exc:
                problems.append(f"no PARAM_VALUE after the flood: {exc}")
            st1 = _sys_status(link)
            if st0 is None or st1 is None:
                problems.append("no SYS_STATUS around the flood")
            else:
                row["wall_overruns_during"] = st1.errors_count2 - st0.errors_count2
                if wall_strict and st1.errors_count2 > st0.errors_count2:
                    problems.append(f"{row['wall_overruns_during']} control periods lost during the flood")
            row["problems"] = problems
            rows.append(row)
            res.check(problems, f"flood {kind}")
            if progress is not None:
                progress.update(1)

    with tempfile.TemporaryDirectory(prefix="qnav-floods-") as tmp, \
            driving_robot(Path(tmp), seed, duration_s, big_file=True) as ctx:
        _as_operator(ctx["robot"].url, ctx["problems"], each_flood)
    st = ctx.get("stats")
    end = list(ctx["problems"]) + (run_problems(st, wall_strict) if st else [])
    res.check(end, "end of run")
    res.figures["floods"] = rows
    if st:
        res.figures["robot"] = {k: v for k, v in st.items() if k != "transitions"}


# --- GCS failsafe under garbage -------------------------------------------------------------

class _Garbage(threading.Thread):
    """Malformed MAVLink from another system id, ~`rate_hz` frames/s until stopped."""

    def __init__(self, url: str, seed: int, rate_hz: float = 500.0) -> None:
        super().__init__(name="garbage", daemon=True)
        from pymavlink import mavutil

        self.conn = mavutil.mavlink_connection(url, source_system=77, source_component=190, dialect=DIALECT)
        self.m = self.conn.mav
        self.rng = random.Random(seed)
        self.rate_hz = rate_hz
        self.stop = threading.Event()
        self.sent: dict[str, int] = {}

    def _frame(self) -> tuple[str, bytes]:
        rng, mav = self.rng, self.m
        bad = rng.choice((math.nan, math.inf, -math.inf))
        r = rng.random()
        if r < 0.35:
            seq = rng.randrange(2)
            if seq == 0 and rng.random() < 0.5:
                return "mission_count", mav.mission_count_encode(1, 1, 2).pack(mav)
            return "nan_mission_item", mav.mission_item_encode(1, 1, seq, 1, 16, 0, 1, 0, 0, 0, 0, bad,
                                                                rng.choice((bad, 1.0)), 0).pack(mav)
        if r < 0.45:
            return "nan_goal", mav.set_position_target_local_ned_encode(0, 1, 1, 1, 0, bad, bad, 0, 0, 0, 0, 0, 0,
                                                                         0, 0, 0).pack(mav)
        if r < 0.55:
            return "nan_param", mav.param_set_encode(1, 1, b"FS_GCS_TOUT_MS", bad, 6).pack(mav)
        if r < 0.65:
            return "nan_command", mav.command_long_encode(1, 1, rng.choice((400, 176, 300, 31000)), 0,
                                                          bad, bad, bad, bad, bad, bad, bad).pack(mav)
        if r < 0.75:
            return "random_bytes", rng.randbytes(rng.randint(1, 280))
        frame = mav.mission_item_int_encode(1, 1, 0, 1, 16, 0, 1, 0, 0, 0, 0, 2**31 - 1, -2**31, 0).pack(mav)
        if r < 0.88:
            return "truncated", frame[:rng.randint(1, len(frame) - 1)]
        buf = bytearray(frame)
        buf[-1] ^= 0xFF
        return "bad_crc", bytes(buf)

    def run(self) -> None:
        t0 = time.monotonic()
        n = 0
        while not self.stop.is_set():
            kind, data = self._frame()
            with suppress(OSError):
                self.conn.write(data)
            self.sent[kind] = self.sent.get(kind, 0) + 1
            n += 1
            if n % 10 == 0:
                time.sleep(max(0.0, t0 + n / self.rate_hz - time.monotonic()))
        self.conn.close()


def _silent_in_garbage(link: Any, beats: _Heartbeats, url: str, seed: int, row: dict[str, Any]) -> None:
    """One run of `failsafe_garbage` on the armed robot: garbage with the heartbeats, then the
    heartbeats stop and the garbage goes on through the failsafe timeout."""
    garbage = _Garbage(url, seed)
    garbage.start()
    try:
        time.sleep(1.0 + random.Random(seed).random())  # garbage and heartbeats together
        beats.stop.set()
        beats.join(2)
        time.sleep(FS_TIMEOUT_MS / 1000 + 1.5)  # garbage goes on through the timeout
    finally:
        garbage.stop.set()
        garbage.join(2)
        row["garbage_sent"] = garbage.sent


@register("failsafe_garbage", small=1, large=5, unit="runs",
          what="GCS heartbeats stop while malformed frames flood in: Hold within timeout + 1 period")
def failsafe_garbage(res: ScenarioResult, count: int, seed: int, progress: Any,
                     duration_s: float = 60.0, wall_strict: bool = False) -> None:
    runs = []
    for i in trials(count, progress):
        s = seed * 1000 + i
        problems: list[str] = []
        row: dict[str, Any] = {"seed": s}
        with tempfile.TemporaryDirectory(prefix="qnav-fsgarbage-") as tmp, \
                driving_robot(Path(tmp), s, duration_s) as ctx:
            _as_operator(ctx["robot"].url, problems, _silent_in_garbage, ctx["robot"].url, s, row,
                         params=(("FS_GCS_TOUT_MS", FS_TIMEOUT_MS), ("FS_GCS_ACTION", 1)))
        problems += ctx["problems"]
        st = ctx.get("stats")
        if st:
            problems += check_failsafe_timing(st, FS_TIMEOUT_MS)
            problems += [p for p in run_problems(st, wall_strict) if "never drove" not in p]
            row.update({k: st.get(k) for k in ("gcs_last_heartbeat_us", "failsafe_since_us", "link_handler_errors",
                                                "tick_p99_us", "compute_p99_us", "lag_max_us", "wall_overruns")})
            tr = _failsafe_transition(st)
            if tr is not None and st.get("gcs_last_heartbeat_us") is not None:
                row["failsafe_after_ms"] = (tr[0] - st["gcs_last_heartbeat_us"]) / 1000
        row["problems"] = problems
        runs.append(row)
        res.check(problems, f"run {i} seed {s}")
    res.figures["runs"] = runs


def _failsafe_transition(st: dict[str, Any]) -> list[Any] | None:
    last = st.get("gcs_last_heartbeat_us")
    return next((t for t in st.get("transitions", []) if last is not None and t[0] > last
                 and t[2] == "HOLD" and "failsafe" in t[3]), None)


def check_failsafe_timing(st: dict[str, Any], timeout_ms: int) -> list[str]:
    """HOLD ("GCS failsafe") after the timeout, within timeout + one period of the last heartbeat."""
    last = st.get("gcs_last_heartbeat_us")
    if last is None:
        return ["the robot recorded no GCS heartbeat"]
    before = [t for t in st.get("transitions", []) if t[0] <= last]
    if not before or before[-1][2] != "DRIVING":
        return [f"setup: not DRIVING at the last heartbeat ({before[-1:]})"]
    tr = _failsafe_transition(st)
    deadline = last + timeout_ms * 1000 + st["period_us"]
    if tr is None:
        return [f"no GCS failsafe HOLD after the last heartbeat at {last} us (transitions "
                f"{[t for t in st.get('transitions', []) if t[0] > last][:3]})"]
    if tr[0] <= last + timeout_ms * 1000:
        return [f"failsafe at {tr[0]} us, before the {timeout_ms} ms timeout ran out"]
    if tr[0] > deadline:
        return [f"failsafe at {tr[0]} us, {(tr[0] - deadline) / 1000:.0f} ms after timeout + one period"]
    return []
