"""The holes hostile testing found in the robot (issue 13), one scenario each.

CAN (lockstep, `rigs.lockstep.LockstepRig`: the pymunk plant and the real
RobotNode + Controller on a python-can virtual bus, shipped paper10 cell
policy from a seeded start, fault injected while DRIVING, as can_faults):

- `can_future_tick`: one forged SimTick with the next counter and a
  far-future time (up to 2^40 us). It is dropped (`SimClock.refused_jumps`),
  every real tick is still answered, no FAULT; sensors cut afterwards are
  still detected: zero command and FAULT within timeout + one period.
- `can_encoder_jump`: EncoderCounts jump by a seeded amount (3000 ticks ..
  2^26) from one tick on: FAULT "encoder jump" at that very tick, zero
  commands from it, the pose estimate moves < 100 mm, ticks go on.
- `can_frozen_sensor`: one sensor board (ranges 0/1, encoders, bumper)
  re-sends its last frame, byte for byte, from a seeded moment: zero command
  and FAULT "... frozen" within SENS_TIMEOUT_MS + one period of its last new
  sample, ticks go on.

MAVLink (the real `MavNode`, polled from the ticking thread after every
tick as the qnav-robot extension does, over the rig's Controller; frames go
through pymavlink's parser):

- `mav_failsafe_garbage`: the operator's GCS stops beating while, every
  tick, NaN/inf MISSION_ITEMs, NaN COMMAND_LONGs, out-of-range goals, random
  bytes and a foreign GCS's heartbeats keep arriving (the foreign one heard
  first, as a router's own heartbeat can be: issue 29 finding 2): the
  failsafe trips within FS_GCS_TOUT_MS + one period of the last own
  heartbeat, the vehicle holds, no handler raised.
- `mav_signing_bounds`: with a key, a key holder's frame stamped near 2^48
  (or far ahead) is dropped; a correct GCS's frames are answered and the
  robot's signed replies pass the GCS's own pymavlink signature and
  timestamp check, before and after a restart (with or without the last
  save: kill -9); a frame captured before the restart is refused after it;
  an unsigned SETUP_SIGNING from the network is refused while
  SIGN_NET_SETUP=0 and accepted once set on the robot.
- `ftp_sessions_quota`: another system id cannot write to, terminate
  (commit), read or reset a client's session; idle sessions of others do
  not lock a new client out for more than a second; a sparse write and a
  huge TruncateFile are refused without allocating (ENOSPC/EINVAL, fast);
  the file and directory quotas hold.
"""

from __future__ import annotations

import contextlib
import math
import queue
import random
import tempfile
import time
from pathlib import Path
from typing import Any

from firmware_py import can_protocol as cp
from firmware_py.mavlink.dialect import NAME as DIALECT
from firmware_py.vehicle import CtrlState
from ground_station.lab.faults.can_faults import (
    _drive_stale,
    _drive_to,
    _edit_after,
    _episodes,
    _fault_at,
    _fault_by,
    _fault_time,
    _first_fault,
    _setup,
    _stale_deadline,
    _stale_episodes,
)
from ground_station.lab.faults.common import RobotProcess, ScenarioResult, register, trials
from ground_station.lab.faults.hostile_mav import _dialect
from ground_station.lab.rigs.lockstep import PERIOD_US, SENSOR_FRAMES
from ground_station.mavlink.link import GCS_COMPID, GCS_SYSID

GCS = (GCS_SYSID, GCS_COMPID)  # the ground station qnav is
FOREIGN_GCS = (77, GCS_COMPID)


# --- CAN ------------------------------------------------------------------------------------------

@register("can_future_tick", small=2, large=40, unit="episodes",
          what="forged far-future SimTick dropped: every tick answered, no FAULT; later sensor cut still detected")
def future_tick(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    refused = 0
    for i in trials(count, progress):
        rng, rig = _setup(seed * 7919 + 5000 + i)
        t_forge = _fault_time(rng)
        forged_us = rng.choice((10**9, 10**12, (1 << 40) - 1)) - rng.randrange(1000)
        timeout_us = rig.ctrl.cfg.sensor_timeout_ms * 1000
        problems: list[str] = []
        with rig:
            _drive_to(rig, t_forge, "at the forgery", problems)
            rig.send(cp.sim_tick(rig.plant.tick, forged_us))  # the next counter, far ahead
            rig.run_until(t_forge + 8 * PERIOD_US)  # raises if a tick goes unanswered
            if rig.node.clock.now_us() != rig.time_us - PERIOD_US:
                problems.append(f"clock {rig.node.clock.now_us()} us, sim {rig.time_us - PERIOD_US} us")
            n_refused = rig.node.clock.refused_jumps + rig.node.tick_gate.refused
            if n_refused != 1:
                problems.append(f"refused {n_refused} ticks, expected 1")
            if _first_fault(rig, t_forge) is not None:
                problems.append(f"FAULT after the forged tick: {rig.ctrl.fault}")
            t_cut = rig.time_us
            deadline = _stale_deadline(t_cut, timeout_us)

            def cut(_tick, t_us, frames, t_cut=t_cut):
                return frames if t_us < t_cut else [
                    f for f in frames if cp.frame_name(f.arbitration_id) not in SENSOR_FRAMES]

            rig.run_until(deadline + 3 * PERIOD_US, frames_hook=cut)
            refused += rig.node.clock.refused_jumps + rig.node.tick_gate.refused
        problems += [f"sensor cut after the forgery: {p}" for p in _fault_by(rig, t_cut, deadline)]
        res.check(problems, f"seed {seed}/{i} forged {forged_us} us at {t_forge} us")
    res.figures["refused_jumps"] = refused


@register("can_forged_tick_pace", small=2, large=20, unit="episodes",
          what="a forged next SimTick 240 ms ahead every 0.5 s for 4 s (under the jump bound): refused, "
               "every real tick answered, clock = sim time, no FAULT")
def forged_tick_pace(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    """Issue 29 finding 6: before the tick gate, each forged tick moved the
    clock 240 ms ahead; the real ticks then counted as repeats or stood still,
    75 ticks were lost and the motor driver's watchdog tripped at 4 s."""
    for i, _, rig, t0 in _episodes(count, seed * 7919 + 9000, progress):
        problems: list[str] = []
        forged = 0
        with rig:
            _drive_to(rig, t0, "at the first forgery", problems)
            for k in range(8):
                rig.send(cp.sim_tick(rig.plant.tick, rig.node.clock.now_us() + 240_000))  # next counter, 240 ms on
                forged += 1
                rig.run_until(t0 + (k + 1) * 500_000)  # raises if a tick goes unanswered
            if rig.node.clock.now_us() != rig.time_us - PERIOD_US:
                problems.append(f"clock {rig.node.clock.now_us()} us, sim {rig.time_us - PERIOD_US} us")
            n_refused = rig.node.tick_gate.refused + rig.node.clock.refused_jumps
            if n_refused != forged:
                problems.append(f"refused {n_refused} of {forged} forged ticks")
            if rig.node.overruns:
                problems.append(f"{rig.node.overruns} ticks lost")
            fault = _first_fault(rig, t0)
            if fault is not None:
                problems.append(f"FAULT after the forged ticks: {rig.ctrl.fault}")
        res.figures["refused"] = res.figures.get("refused", 0) + n_refused
        res.check(problems, f"seed {seed}/{i} forged from {t0} us")


@register("can_encoder_jump", small=2, large=40, unit="episodes",
          what="encoder counts jump -> FAULT with the reason and zero command at that tick, pose kept")
def encoder_jump(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    for i, rng, rig, t_jump in _episodes(count, seed * 7919 + 6000, progress):
        jump = rng.choice((3000, -3000, 10**6, -(10**6), 1 << 26)) * rng.choice((1, 1, 2))
        side = rng.choice(("Enc_Left", "Enc_Right"))

        def jump_counts(sig, jump=jump, side=side):
            sig[side] = cp.wrap_counts(sig[side] + jump)  # the offset stays, as a glitched encoder's

        hook = _edit_after(t_jump, "EncoderCounts", jump_counts)

        problems: list[str] = []
        with rig:
            _drive_to(rig, t_jump, "at the jump", problems, frames_hook=hook)
            pose = rig.ctrl.odom.pose_mm()
            rig.run_until(t_jump + 6 * PERIOD_US, frames_hook=hook)
            moved = math.hypot(rig.ctrl.odom.x_mm - pose[0], rig.ctrl.odom.y_mm - pose[1])
        problems += _fault_at(rig, t_jump, "encoder jump")
        if moved >= 100:
            problems.append(f"pose estimate moved {moved:.0f} mm after the jump")
        res.check(problems, f"seed {seed}/{i} {side} +{jump} ticks at {t_jump} us")


@register("can_frozen_sensor", small=3, large=60, unit="episodes",
          what="a board re-sends one frame forever -> zero command and FAULT '... frozen' within timeout + 1 period")
def frozen_sensor(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    names = [*sorted(SENSOR_FRAMES), "MotorStatus"]  # the driver status carries a rolling counter too
    for i, pick, rig, t_freeze, timeout_ms in _stale_episodes(count, seed * 7919 + 7000, progress):
        name = pick.choice(names)
        fid = cp.FRAME_IDS[name]
        last: list = []

        def hook(_tick, t_us, frames, t_freeze=t_freeze, fid=fid, last=last):
            out = []
            for f in frames:
                if f.arbitration_id == fid:
                    if t_us < t_freeze:
                        last[:] = [f]
                    else:  # stuck: the same bytes again, counter and all
                        f = last[0]
                out.append(f)
            return out

        problems, deadline = _drive_stale(rig, t_freeze, timeout_ms, "at the freeze", hook)
        fault = _first_fault(rig, t_freeze)
        if fault is None or fault.t_us > deadline or "frozen" not in fault.cause:
            problems.append(f"no FAULT '... frozen' by {deadline} us ({fault})")
        else:  # detection time past the timeout, from the last sample whose counter advanced
            late = fault.t_us - (t_freeze - PERIOD_US) - timeout_ms * 1000
            res.figures["max_us_after_timeout"] = max(res.figures.get("max_us_after_timeout", 0), late)
        res.check(problems, f"seed {seed}/{i} {name} frozen at {t_freeze} us, timeout {timeout_ms} ms")


# --- MAVLink ---------------------------------------------------------------------------------------

class _PolledNode:
    """A MavNode over the rig's controller, polled after every tick from the
    ticking thread (as firmware_py.mavlink.extension does) with the raw
    frames queued for it; errors in the poll are recorded, never lost."""

    def __init__(self, rig, fs_timeout_ms: int) -> None:
        from firmware_py.mavlink.node import MavNode
        from firmware_py.mavlink.params import ParamStore
        from firmware_py.mavlink.signing import Signing

        self.m = _dialect()
        self.node = MavNode(rig.ctrl, ParamStore(None), Signing(None))
        self.node.boot(0)
        ok, why = self.node.params.set("FS_GCS_TOUT_MS", fs_timeout_ms)
        assert ok, why
        self.node._apply_params(reboot=False)
        self.parser = self.m.MAVLink(None)
        self.parser.robust_parsing = True  # as pymavlink's mavutil connections parse (the robot's shell)
        self.inbox: queue.Queue[bytes] = queue.Queue()
        self.errors: list[str] = []
        self.failsafe_at: int | None = None
        self.texts: list[str] = []  # the robot's STATUSTEXTs (refusal reasons), in order
        self.clock = rig.node.clock
        rig.node.after_tick.append(self.poll)

    def poll(self, _out: object) -> None:
        now = self.clock.now_us()
        try:
            while True:
                try:
                    data = self.inbox.get_nowait()
                except queue.Empty:
                    break
                for b in data:
                    msg = self.parser.parse_char(bytes([b]))
                    if msg is not None:
                        self._keep_texts(self.node.handle(msg, now))
            self._keep_texts(self.node.tick(now))
        except Exception as exc:  # the point of the scenario: this must never happen
            self.errors.append(f"{type(exc).__name__}: {exc}")
        if self.node.failsafe and self.failsafe_at is None:
            self.failsafe_at = now

    def _keep_texts(self, replies: list) -> None:
        self.texts += [r.text for r in replies if r.get_type() == "STATUSTEXT"]


def _garbage(m, rng: random.Random, codec) -> list[bytes]:
    """One tick's worth of malformed MAVLink (every message parses; its fields are hostile)."""
    bad = rng.choice((math.nan, math.inf, -math.inf))
    out = [
        codec.mission_count_encode(1, 1, 1, 0),
        codec.mission_item_encode(1, 1, 0, m.MAV_FRAME_LOCAL_NED, m.MAV_CMD_NAV_WAYPOINT, 0, 1,
                                  0, 0, 0, 0, bad, rng.choice((bad, 1.0)), 0, 0),
        codec.command_long_encode(1, 1, rng.choice((176, 400, 511, 512, 246)), 0, bad, bad, bad, bad, 0, 0, 0),
        codec.set_position_target_local_ned_encode(0, 1, 1, m.MAV_FRAME_LOCAL_NED, 0, bad, bad, 0,
                                                   0, 0, 0, 0, 0, 0, 0, 0),
        codec.set_position_target_global_int_encode(0, 1, 1, m.MAV_FRAME_GLOBAL_INT, 0, 2**31 - 1, -2**31,
                                                    0, 0, 0, 0, 0, 0, 0, 0, 0),
        codec.param_set_encode(1, 1, b"FS_GCS_TOUT_MS", bad, 6),
    ]
    frames = [bytes(x.pack(codec)) for x in out]
    frames.append(rng.randbytes(rng.randint(1, 60)))
    return frames


@register("mav_failsafe_garbage", small=2, large=20, unit="episodes",
          what="own GCS silent, malformed frames + foreign GCS heartbeats every tick -> failsafe in timeout + 1 period")
def failsafe_garbage(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    m = _dialect()
    for i in trials(count, progress):  # the failsafe timeout is drawn before the fault time
        rng, rig = _setup(seed * 7919 + 8000 + i)
        fs_ms = rng.choice((500, 1000))
        t_silent = _fault_time(rng)
        gcs, foreign = m.MAVLink(None, *GCS), m.MAVLink(None, *FOREIGN_GCS)
        problems: list[str] = []
        last_hb = -1
        with rig:
            polled = _PolledNode(rig, fs_ms)
            while rig.time_us < t_silent + fs_ms * 1000 + 4 * PERIOD_US:
                # the foreign heartbeat first: with "the first GCS heard owns the failsafe" it
                # would own it and the silence of the operator's GCS would never trip it
                data = bytes(foreign.heartbeat_encode(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                             .pack(foreign))
                if rig.time_us < t_silent:
                    data += bytes(gcs.heartbeat_encode(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                                  .pack(gcs))  # handled at this tick's time
                    last_hb = rig.time_us
                data += b"".join(_garbage(m, rng, gcs))  # after the heartbeats: random bytes could swallow a frame
                polled.inbox.put(data)
                rig.tick()
            state = rig.ctrl.state
        if polled.errors:
            problems.append(f"poll raised: {polled.errors[0]}")
        if polled.node.handler_errors:
            problems.append(f"handler exceptions: {polled.node.handler_errors}")
        # the heartbeat's own handling time: the poll after a tick may run while the
        # next tick's frames are queued, so the node's record is the reference
        handled = polled.node.gcs_last_heartbeat_us
        if handled is None or handled > last_hb:
            problems.append(f"last heartbeat counted at {handled} us, the own GCS's last was sent at {last_hb} us")
        else:
            last_hb = handled
        fs_at = polled.failsafe_at
        if fs_at is None or not fs_ms * 1000 < fs_at - last_hb <= fs_ms * 1000 + PERIOD_US:
            problems.append(f"failsafe at {fs_at} us, last own heartbeat {last_hb} us, timeout {fs_ms} ms")
        else:
            late = fs_at - last_hb - fs_ms * 1000
            res.figures["max_us_after_timeout"] = max(res.figures.get("max_us_after_timeout", 0), late)
        res.figures["foreign_heartbeats"] = res.figures.get("foreign_heartbeats", 0) + \
            polled.node.foreign_gcs_heartbeats
        if state == CtrlState.DRIVING:
            problems.append("still DRIVING after the failsafe")
        if polled.node.foreign_gcs_heartbeats == 0:
            problems.append("the foreign GCS's heartbeats were never seen")
        res.check(problems, f"seed {seed}/{i} silent at {t_silent} us, FS_GCS_TOUT_MS {fs_ms}")


def _signing_node(root: Path, key_file: Path | None, network: bool = True):
    from firmware_py.control.controller import Controller
    from firmware_py.mavlink.node import MavNode
    from firmware_py.mavlink.params import ParamStore
    from firmware_py.mavlink.signing import Signing

    node = MavNode(Controller(), ParamStore(root), Signing(root), network_link=network)
    node.boot(int(time.monotonic() * 1e6), key_file)
    return node


def _exchange(m, node, frame: bytes, gcs_parser) -> list:
    """Feed `frame` to the robot; its replies signed as the robot's shell signs
    them, parsed back by the GCS's own pymavlink (signature + timestamp check)."""
    msg = m.MAVLink(None).parse_char(frame)
    now = int(time.monotonic() * 1e6)
    replies = node.handle(msg, now) if msg is not None else []
    robot = m.MAVLink(None, node.sysid, node.compid)
    if node.signing.key is not None:
        robot.signing.secret_key = node.signing.key
        robot.signing.sign_outgoing = True
        robot.signing.timestamp = node.signing.current_timestamp(now)
    out = []
    for r in replies:
        got = gcs_parser.parse_char(bytes(r.pack(robot)))
        if got is not None and got.get_type() != "BAD_DATA":
            out.append(got)
    if node.signing.key is not None:
        node.signing.note_sent(robot.signing.timestamp)
    return out


def _codec(m, key: bytes, link_id: int, ts: int, sysid: int = GCS[0]):
    """A GCS codec signing with `key` on stream `link_id`, stamping from `ts`."""
    c = m.MAVLink(None, sysid, GCS[1])
    c.signing.secret_key, c.signing.sign_outgoing, c.signing.link_id = key, True, link_id
    c.signing.timestamp = ts
    return c


def _ask(m, c) -> bytes:
    """A REQUEST_MESSAGE (HEARTBEAT) frame from codec `c`: always answered when accepted."""
    return bytes(c.command_long_encode(1, 1, m.MAV_CMD_REQUEST_MESSAGE, 0, 0, 0, 0, 0, 0, 0, 0).pack(c))


@register("mav_signing_bounds", small=2, large=20, unit="restarts",
          what="signed frame near 2^48 dropped; a correct GCS reaches the robot before and after a restart")
def signing_bounds(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    import json

    from firmware_py.mavlink.signing import FUTURE_WINDOW, MAX_TIMESTAMP, wall_timestamp

    m = _dialect()
    rng = random.Random(seed)
    for i in trials(count, progress):
        problems: list[str] = []
        with tempfile.TemporaryDirectory(prefix="qnav-signing-") as tmp:
            root = Path(tmp)
            key = rng.randbytes(32)
            key_file = root / "key.hex"
            key_file.write_text(key.hex())

            gcs_parser = m.MAVLink(None)
            gcs_parser.signing.secret_key = key  # checks the robot's signatures and stream timestamps
            node = _signing_node(root, key_file)
            rogue_ts = rng.choice((MAX_TIMESTAMP - rng.randrange(1, 1000), wall_timestamp() + 10 * FUTURE_WINDOW))
            if _exchange(m, node, _ask(m, _codec(m, key, 3, rogue_ts, sysid=rng.randint(1, 250))), gcs_parser):
                problems.append(f"a frame stamped {rogue_ts} was answered")
            good = _codec(m, key, 1, wall_timestamp())
            captured = _ask(m, good)
            if not _exchange(m, node, captured, gcs_parser):
                problems.append("the correct GCS got no (verifiable) answer before the restart")
            if rng.random() < 0.5:
                node.signing.persist(int(time.monotonic() * 1e6))  # a clean shutdown; else kill -9
            ts_before = node.signing.timestamp
            # a restart takes longer than the robot's stream timestamp can run ahead of the wall clock (the
            # gap between its boot's two clock readings, ms under load): a restart within that gap had a
            # correct GCS drop the robot's first answer as a replay (a fresh-clone make test, once)
            while wall_timestamp() <= ts_before:
                time.sleep(0.001)
            again = _signing_node(root, key_file)
            if again.signing.timestamp >= min(MAX_TIMESTAMP, wall_timestamp() + FUTURE_WINDOW):
                problems.append(f"robot timestamp {again.signing.timestamp} after restart (before {ts_before})")
            if _exchange(m, again, captured, gcs_parser):
                problems.append("a frame captured before the restart was answered after it")
            good.signing.timestamp = max(good.signing.timestamp, wall_timestamp())
            if not _exchange(m, again, _ask(m, good), gcs_parser):
                problems.append("the correct GCS got no (verifiable) answer after the restart")
            # unsigned SETUP_SIGNING over the network on a robot without a key
            bare_root = root / "bare"
            bare = _signing_node(bare_root, None)
            plain = m.MAVLink(None, *GCS)
            setup = bytes(plain.setup_signing_encode(1, 1, list(rng.randbytes(32)), wall_timestamp()).pack(plain))
            _exchange(m, bare, setup, m.MAVLink(None))
            if bare.signing.key is not None:
                problems.append("an unsigned SETUP_SIGNING from the network set a key")
            params = bare_root / "params" / "params.json"
            params.parent.mkdir(parents=True, exist_ok=True)
            params.write_text(json.dumps({"version": 1, "params": {"SIGN_NET_SETUP": 1}}))
            allowed = _signing_node(bare_root, None)
            _exchange(m, allowed, setup, m.MAVLink(None))
            if allowed.signing.key is None:
                problems.append("SETUP_SIGNING refused although SIGN_NET_SETUP=1 on the robot")
        res.check(problems, f"seed {seed}/{i}")


class _Ftp:
    """Requests to an FtpServer from any (sysid, compid), on an injected clock."""

    def __init__(self, server) -> None:
        self.server = server
        self.seq = 0
        self.now = 0

    def req(self, owner: tuple[int, int], op: int, data: bytes = b"", session: int = 0, offset: int = 0) -> list:
        from firmware_py.mavlink.ftp_server import HEADER, PAYLOAD_LEN, parse

        self.seq += 1
        p = HEADER.pack(self.seq & 0xFFFF, session, op, len(data), 0, 0, 0, offset) + data
        return [parse(r) for r in self.server.handle(p.ljust(PAYLOAD_LEN, b"\0"), self.now, owner)]

    @staticmethod
    def is_nak(replies: list, code: int | None = None) -> bool:
        from firmware_py.mavlink.ftp_server import Op

        return bool(replies) and replies[0][2] == Op.NAK and (code is None or replies[0][7][0] == code)


@register("ftp_sessions_quota", small=3, large=50, unit="rounds",
          what="foreign sysid cannot touch a session; idle sessions yield; sparse write / huge truncate refused")
def ftp_sessions_quota(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    from firmware_py.mavlink.ftp_server import FtpServer, Nak, Op
    from firmware_py.storage import Storage

    rng = random.Random(seed)
    slowest_truncate = 0.0
    for i in trials(count, progress):
        problems: list[str] = []
        with tempfile.TemporaryDirectory(prefix="qnav-ftp-") as tmp:
            quota = 1 << 20
            ftp = _Ftp(FtpServer(Storage(tmp, quota_bytes=quota, quota_files=24, quota_dirs=6)))
            server, req, is_nak = ftp.server, ftp.req, ftp.is_nak

            victim = (255, 190)
            thief = (rng.randint(1, 250), rng.randint(0, 255))
            sid = rng.randrange(256)
            body = rng.randbytes(rng.randint(1, 3000))
            if is_nak(req(victim, Op.CREATE_FILE, b"/policies/up.qtab", sid)):
                problems.append("victim could not open its session")
            half = len(body) // 2
            for off in range(0, half, 200):
                req(victim, Op.WRITE_FILE, body[off:min(off + 200, half)], sid, off)
            for op, data in ((Op.WRITE_FILE, b"evil"), (Op.TERMINATE_SESSION, b""), (Op.READ_FILE, b"")):
                if not is_nak(req(thief, op, data, sid), Nak.INVALID_SESSION):
                    problems.append(f"thief's {op.name} on session {sid} was not refused")
            req(thief, Op.RESET_SESSIONS)
            if server.storage.exists("/policies/up.qtab"):
                problems.append("the half-written upload was committed by someone else")
            for off in range(half, len(body), 200):
                if is_nak(req(victim, Op.WRITE_FILE, body[off:off + 200], sid, off)):
                    problems.append("victim's session was broken by the thief")
                    break
            req(victim, Op.TERMINATE_SESSION, b"", sid)
            if not server.storage.exists("/policies/up.qtab") or \
                    server.storage.read_bytes("/policies/up.qtab") != body:
                problems.append("victim's upload is not what it wrote")
            # idle squatters: two systems, two sessions each, then silence
            for k, owner in enumerate(((101, 1), (102, 1))):
                for s in range(2):
                    req(owner, Op.CREATE_FILE, f"/policies/sq{k}{s}".encode(), s)
            idle_us = server.evict_idle_us  # past the server's own eviction age, by 5 % to 2x
            ftp.now += rng.randint(idle_us * 21 // 20, idle_us * 2)
            if is_nak(req(victim, Op.CREATE_FILE, b"/policies/late.qtab", sid)):
                problems.append(f"idle sessions locked a new client out after > {idle_us / 1e6:g} s")
            req(victim, Op.TERMINATE_SESSION, b"", sid)
            # sparse write and huge truncate
            used = server.storage.usage()
            req(victim, Op.CREATE_FILE, b"/policies/sparse", 1)
            if not is_nak(req(victim, Op.WRITE_FILE, b"x", 1, quota - rng.randint(1, 1000)), Nak.FAIL_ERRNO):
                problems.append("a sparse write at the end of the quota was accepted")
            req(victim, Op.TERMINATE_SESSION, b"", 1)
            t0 = time.perf_counter()
            r = req(victim, Op.TRUNCATE_FILE, b"/policies/up.qtab", 0, rng.choice((0xFFFFFFFF, quota + 1, 2**31)))
            slowest_truncate = max(slowest_truncate, time.perf_counter() - t0)
            if not is_nak(r, Nak.FAIL_ERRNO) or r[0][7][1] != 28:
                problems.append(f"huge truncate not refused with ENOSPC: {r}")
            if server.storage.usage() > used + 1000:
                problems.append(f"quota used grew by {server.storage.usage() - used} bytes")
            # file quota: keep creating until refused
            made = 0
            while made < 100:
                r = req(victim, Op.CREATE_FILE, f"/f{made}".encode(), 2)
                if is_nak(r):
                    break
                req(victim, Op.TERMINATE_SESSION, b"", 2)
                made += 1
            files, _dirs = server.storage.counts()
            if made >= 100 or files > 24:
                problems.append(f"file quota of 24 not enforced: {made} created, {files} files")
            server.close()
        res.check(problems, f"seed {seed}/{i} thief {thief} session {sid}")
    res.figures["slowest_huge_truncate_ms"] = round(slowest_truncate * 1000, 3)


@register("mav_signing_process", small=1, large=5, unit="kill -9 + restart of qnav-robot",
          what="signed frames stamped near 2^48 at a running qnav-robot: a correct GCS still reaches it, "
               "also after kill -9 and a restart")
def signing_process(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    """The whole robot (`qnav-robot --signing-key`, UDP, its own storage): a key
    holder with a clock near 2^48 sends signed frames; the operator's `Link`
    (pymavlink, checking the robot's signatures and timestamps) must still
    read parameters from it, after a kill -9 and a restart too."""
    import json

    from firmware_py.mavlink.signing import MAX_TIMESTAMP, load_key_file
    from ground_station.mavlink.link import Link, mavutil

    rng = random.Random(seed)
    mu = mavutil()
    for i in trials(count, progress):
        problems: list[str] = []
        with tempfile.TemporaryDirectory(prefix="qnav-signproc-") as tmp:
            root = Path(tmp)
            key_file = root / "key.txt"
            key_file.write_text(rng.randbytes(16).hex() + "-passphrase\n")
            key = load_key_file(key_file)
            robot = RobotProcess(root / "robot", key_file=key_file, log=root / "robot.log").start()
            links: list = []
            try:
                link = Link(robot.url, signing_key=key_file, tlog=False)
                links.append(link)
                link.connect(30.0)
                rogue = mu.mavlink_connection(robot.url, source_system=rng.randint(1, 250), source_component=190,
                                              dialect=DIALECT)
                links.append(rogue)
                rogue.setup_signing(key, sign_outgoing=True, link_id=7,
                                    initial_timestamp=MAX_TIMESTAMP - rng.randrange(2, 30))
                for _ in range(20):
                    rogue.mav.command_long_send(1, 1, mu.mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 0, 0, 0, 0, 0, 0, 0)
                    rogue.mav.signing.timestamp = min(rogue.mav.signing.timestamp, MAX_TIMESTAMP - 1)
                time.sleep(1.0)  # the robot's telemetry would carry its timestamps past 2^48 (wrap)
                if link.read_params(("SYSID_THISMAV",), budget_s=5.0)["SYSID_THISMAV"] is None:
                    problems.append("the correct GCS lost the robot after the 2^48 frames")
                robot.kill9()
                for c in links:
                    with contextlib.suppress(Exception):
                        c.close()
                links.clear()
                state_file = root / "robot" / "params" / "signing.json"
                state: dict[str, Any] = json.loads(state_file.read_text()) if state_file.exists() else \
                    {"timestamp": 0, "streams": []}
                if state["timestamp"] > MAX_TIMESTAMP or any(s[-1] > MAX_TIMESTAMP for s in state["streams"]):
                    problems.append("signing state beyond 2^48 - 1 on disk")
                robot.start()  # the restart, on the same storage
                link = Link(robot.url, signing_key=key_file, tlog=False)
                links.append(link)
                link.connect(30.0)
                if link.read_params(("SYSID_THISMAV",), budget_s=5.0)["SYSID_THISMAV"] is None:
                    problems.append("the correct GCS cannot reach the robot after kill -9 and a restart")
            except Exception as exc:  # a connect that times out is the failure being looked for
                problems.append(f"{type(exc).__name__}: {exc}")
            finally:
                for c in links:
                    with contextlib.suppress(Exception):
                        c.close()
                robot.stop()
        res.check(problems, f"seed {seed}/{i}")


