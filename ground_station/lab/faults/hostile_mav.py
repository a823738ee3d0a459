"""Hostile MAVLink input against the robot's MAVLink node with signing on.

The robot side is the real thing minus sockets: `MavNode` (signing filter,
params, commands, missions, goals, FTP routing) over the real `Controller`
as its vehicle, `FtpServer` on a `Storage` root (activation through the
controller's loader, as on the robot), `ParamStore`/`Signing` persisted in
that root; a PREFLIGHT_REBOOT reloads the policy from storage. Frames go
through pymavlink's own parser set up as the robot's shell sets it, then
`handle`; `tick` runs every 50 frames.

Frames (seeded): random bytes; signed frames of the node's message types
with random field values (SETUP_SIGNING excepted: a key holder may change
the key; in-range sets of SYSID_THISMAV/MAV_COMPID/SIGN_REQUIRE excepted,
they lock the fuzzer out by design); hostile FTP payloads (size fields beyond
the data or above 239, unknown opcodes, huge offsets, path escapes through
`..`, absolute paths, symlinks placed in the root, temp names, control
characters; writes past the quota; renames onto the protected and active
names, garbage and corrupted policies activated); out-of-range, NaN and
fractional PARAM_SETs; the same frames unsigned, signed with a wrong key,
and replayed.

Invariants, per frame: no exception anywhere on the path; an unsigned
(non-RADIO_STATUS) frame is dropped and counted, a badly signed one too,
a replay is dropped as a replay; every parameter stays inside its range;
a signed FTP request gets an answer; the controller's policy is always the
one in active.qtab and that file always loads. Every 500 frames and at the
end: nothing outside the storage root changed, the stored params load
without a warning.
"""

from __future__ import annotations

import math
import os
import random
import struct
import tempfile
from pathlib import Path
from typing import Any

from ground_station.lab.faults.common import RobotProcess, ScenarioResult, register, trials
from ground_station.mavlink.link import GCS_COMPID, GCS_SYSID

GCS = (GCS_SYSID, GCS_COMPID)
FTP_PATHS = (
    "/policies/x.qtab", "policies/y.qtab", "/policies/active.qtab", "/policies/last_good.qtab",
    "/params/params.json", "/params/signing.json", "/", "", ".", "..", "../x", "/../x", "/policies/../../x",
    "/policies/../../../../etc/passwd", "/etc/passwd", "//etc/passwd", "/policies/evil/passwd",
    "/link.qtab", "/policies/evil", "/policies/.qnav-tmp-x", "/a\x01b", "/a\\..\\b", "/policies/" + "a" * 230,
    "/new_dir", "/new_dir/f", "/params", "/policies", "/\xff\xfe", "/policies/x.qtab\0/etc/passwd",
)


def _float(rng: random.Random) -> float:
    r = rng.random()
    if r < 0.1:
        return rng.choice((math.nan, math.inf, -math.inf, 3.4e38, -3.4e38, 1e-45))
    if r < 0.5:
        return float(rng.randint(-5, 600))
    return rng.uniform(-1e6, 1e6)


_INT_RANGES = {"uint8_t": (0, 255), "int8_t": (-128, 127), "uint16_t": (0, 65535),
               "int16_t": (-32768, 32767), "uint32_t": (0, 2**32 - 1), "int32_t": (-2**31, 2**31 - 1),
               "uint64_t": (0, 2**64 - 1), "int64_t": (-2**63, 2**63 - 1)}


def _value(rng: random.Random, ftype: str, length: int):
    if ftype == "char":
        return rng.randbytes(rng.randint(0, max(1, length)))
    if ftype in ("float", "double"):
        one = _float
    else:
        lo, hi = _INT_RANGES[ftype]
        def one(r, lo=lo, hi=hi):
            return r.choice((lo, hi, 0, 1)) if r.random() < 0.2 else r.randint(lo, hi)
    if length:
        return [one(rng) for _ in range(length)]
    return one(rng)


def _dialect():
    """The robot's dialect (firmware_py.mavlink.dialect) in MAVLink 2, as its node uses it."""
    os.environ["MAVLINK20"] = "1"
    from firmware_py.mavlink.dialect import mavlink2

    return mavlink2


class FrameMaker:
    """Seeded hostile frames; keeps the signed ones for replays."""

    ROUTED = ("HEARTBEAT", "PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET", "COMMAND_LONG",
              "COMMAND_INT", "SET_MODE", "MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ITEM",
              "MISSION_REQUEST_LIST", "MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK",
              "MISSION_CLEAR_ALL", "MISSION_SET_CURRENT", "SET_POSITION_TARGET_LOCAL_NED",
              "SET_POSITION_TARGET_GLOBAL_INT", "RADIO_STATUS", "FILE_TRANSFER_PROTOCOL")
    COMMANDS = (400, 176, 511, 512, 246, 300, 183, 31000)  # arm, mode, intervals, reboot, mission start, ...

    def __init__(self, rng: random.Random, key: bytes, good_policy: bytes) -> None:
        from firmware_py.mavlink.signing import wall_timestamp

        m = _dialect()
        self.m, self.rng, self.good_policy = m, rng, good_policy
        self.classes = {c.msgname: c for c in m.mavlink_map.values()}
        self.signed = m.MAVLink(None, *GCS)
        self.signed.signing.secret_key = key
        self.signed.signing.sign_outgoing = True
        self.signed.signing.link_id = 1
        self.signed.signing.timestamp = wall_timestamp()
        self.plain = m.MAVLink(None, *GCS)
        self.wrong = m.MAVLink(None, *GCS)
        self.wrong.signing.secret_key = bytes(32)
        self.wrong.signing.sign_outgoing = True
        self.wrong.signing.timestamp = wall_timestamp() + 10**9
        self.sent_signed: list[bytes] = []
        self.ftp_seq = 0
        self.script: list = []  # pending frames of a multi-frame FTP sequence

    # --- messages ---------------------------------------------------------------
    def random_message(self, name: str | None = None):
        rng, m = self.rng, self.m
        if name is None:
            name = rng.choice(self.ROUTED) if rng.random() < 0.85 else rng.choice(sorted(self.classes))
            if name == "SETUP_SIGNING":
                name = "HEARTBEAT"
        if name == "PARAM_SET":
            return self.param_set()
        if name == "FILE_TRANSFER_PROTOCOL":
            return self.ftp(self.ftp_payload())
        cls = self.classes[name]
        vals = {}
        for fname, ftype, n in zip(cls.fieldnames, cls.fieldtypes, cls.array_lengths, strict=True):
            vals[fname] = _value(rng, ftype, n)
        for f, ours in (("target_system", (0, 1)), ("target_component", (0, 1))):
            if f in vals and rng.random() < 0.8:
                vals[f] = rng.choice(ours)
        if name in ("COMMAND_LONG", "COMMAND_INT") and rng.random() < 0.7:
            vals["command"] = rng.choice(self.COMMANDS)
            if rng.random() < 0.6:  # the values these commands act on (arm, reboot, mode flag)
                vals["param1"] = rng.choice((0.0, 1.0, 1.0, 2.0))
            if rng.random() < 0.5:
                vals["param2"] = rng.choice((0.0, 4.0, 10.0, 15.0, 21196.0))
        if name == "HEARTBEAT" and rng.random() < 0.5:
            vals["type"] = m.MAV_TYPE_GCS
        return cls(*[vals[f] for f in cls.fieldnames])

    def param_set(self):
        from firmware_py.mavlink.params import PARAMS

        rng = self.rng
        d = rng.choice(PARAMS)
        r = rng.random()
        if d.name in ("SYSID_THISMAV", "MAV_COMPID", "SIGN_REQUIRE") or r < 0.4:
            value = rng.choice((d.min - 1, d.max + 1, d.max * 2 + 7, -2**31, 2**31))
        elif r < 0.55:
            value = rng.choice((math.nan, math.inf, -math.inf, d.min + 0.5))
        elif r < 0.75:
            value = rng.randint(d.min, d.max)
        else:
            value = _float(rng)
        name = d.name.encode() if rng.random() < 0.9 else rng.randbytes(rng.randint(0, 16))
        return self.m.MAVLink_param_set_message(1, 1, name, value, 6)

    # --- FTP ----------------------------------------------------------------------
    def ftp(self, payload: bytes):
        payload = payload[:251].ljust(251, b"\0")
        return self.m.MAVLink_file_transfer_protocol_message(0, 1, self.rng.choice((0, 1, 1, 1)), list(payload))

    def _hdr(self, opcode: int, data: bytes, *, session: int = 0, offset: int = 0,
             size: int | None = None) -> bytes:
        self.ftp_seq = (self.ftp_seq + 1) & 0xFFFF
        n = len(data) if size is None else size
        return struct.pack("<HBBBBBBI", self.ftp_seq, session, opcode, n & 0xFF, 0, 0, 0,
                           offset & 0xFFFFFFFF) + data

    def ftp_payload(self) -> bytes:
        rng = self.rng
        r = rng.random()
        if r < 0.05:
            return rng.randbytes(rng.randint(0, 251))
        opcode = rng.randint(0, 16) if r < 0.8 else rng.choice((17, 42, 127, 128, 129, 200, 255))
        path = rng.choice(FTP_PATHS)
        if opcode == 13:  # rename old\0new
            data = f"{rng.choice(FTP_PATHS)}\0{rng.choice(FTP_PATHS)}".encode("utf-8", "surrogateescape")
        elif opcode == 7:
            data = rng.randbytes(rng.randint(0, 239))
        else:
            data = path.encode("utf-8", "surrogateescape")
        if rng.random() < 0.3:
            data = data + rng.randbytes(rng.randint(0, 20))
        data = data[:239]
        s = rng.random()
        size = None if s < 0.5 else rng.randint(len(data) + 1, 255) if s < 0.8 else rng.randint(0, 255)
        o = rng.random()
        offset = (0 if o < 0.4 else rng.choice((0xFFFFFFFF, 0xFFFFFF00, 2**31, 8 * 1024 * 1024 - 100))
                  if o < 0.6 else rng.randint(0, 300_000) if o < 0.8 else rng.randrange(2**32))
        return self._hdr(opcode, data, session=rng.choice((0, 0, 1, 2, 3, 5, 255)), offset=offset, size=size)

    def upload_script(self) -> list:
        """A whole upload + activation of a garbage, a corrupted or (rarely) the good policy."""
        rng = self.rng
        r = rng.random()
        if r < 0.4:
            body = rng.randbytes(rng.randint(0, 3000))
        elif r < 0.85:
            flipped = bytearray(self.good_policy)
            for _ in range(rng.randint(1, 4)):
                flipped[rng.randrange(len(flipped))] ^= 1 << rng.randrange(8)
            body = bytes(flipped)
        else:
            body = self.good_policy
        name = f"/policies/up{rng.randrange(4)}.qtab".encode()
        sess = rng.randrange(4)
        frames = [self._hdr(6, name, session=sess)]
        for off in range(0, len(body), 239):
            frames.append(self._hdr(7, body[off:off + 239], session=sess, offset=off))
        frames.append(self._hdr(1, b"", session=sess))
        frames.append(self._hdr(13, name + b"\0/policies/active.qtab"))
        return [self.ftp(p) for p in frames]

    # --- frames -----------------------------------------------------------------
    def next(self) -> tuple[str, bytes, Any]:
        """(kind, bytes, pymavlink message or None)."""
        rng = self.rng
        if self.script:
            msg = self.script.pop(0)
            return "signed", self._sign(msg), msg
        r = rng.random()
        if r < 0.12:
            junk = rng.randbytes(rng.randint(1, 280))
            if rng.random() < 0.5:
                junk = bytes([rng.choice((0xFD, 0xFE))]) + junk
            return "random", junk, None
        if r < 0.14:
            self.script = self.upload_script()
            return self.next()
        if r < 0.22 and self.sent_signed:
            return "replay", rng.choice(self.sent_signed[-200:]), None
        while True:
            msg = self.random_message()
            try:
                msg.pack(self.plain)
                break
            except (struct.error, TypeError, ValueError):
                continue  # a field value pymavlink cannot pack: draw another message
        if r < 0.32:
            return "unsigned", msg.pack(self.plain), msg
        if r < 0.38:
            return "badsig", msg.pack(self.wrong), msg
        if r < 0.45:  # a signed frame with bytes flipped afterwards (CRC or signature breaks)
            buf = bytearray(self._sign(msg))
            for _ in range(rng.randint(1, 3)):
                buf[rng.randrange(len(buf))] = rng.randrange(256)
            return "mutated", bytes(buf), None
        return "signed", self._sign(msg), msg

    def _sign(self, msg) -> bytes:
        buf = msg.pack(self.signed)
        self.sent_signed.append(buf)
        if len(self.sent_signed) > 1000:
            del self.sent_signed[:500]
        return buf


def _outside_snapshot(sandbox: Path, root: Path) -> dict[str, tuple[int, int]]:
    snap = {}
    for dirpath, dirs, files in os.walk(sandbox):
        if Path(dirpath) == root:
            dirs[:] = []
            continue
        for name in files + dirs:
            p = os.path.join(dirpath, name)
            if Path(p) == root:
                continue  # the root's own mtime changes with its contents
            st = os.lstat(p)
            snap[p] = (st.st_size, st.st_mtime_ns)
    return snap


class HostileRig:
    """The robot's MAVLink side with signing on, rooted in a sandbox directory."""

    def __init__(self, sandbox: Path, seed: int) -> None:
        from firmware_py.control.controller import Controller
        from firmware_py.mavlink.ftp_server import FtpServer
        from firmware_py.mavlink.node import MavNode
        from firmware_py.mavlink.params import ParamStore
        from firmware_py.mavlink.signing import Signing
        from firmware_py.policy import load_policy
        from firmware_py.storage import ACTIVE_POLICY, Storage
        from ground_station.lab.rigs.lockstep import CELL_POLICY

        self.sandbox = sandbox
        self.root = sandbox / "robot"
        (sandbox / "etc").mkdir(parents=True)
        (sandbox / "etc" / "passwd").write_text("root:x:0:0\n")
        (sandbox / "victim.txt").write_text("must not change\n")
        self.storage = Storage(self.root, quota_bytes=512 * 1024)
        os.symlink(sandbox / "etc", self.root / "policies" / "evil")
        os.symlink(sandbox / "victim.txt", self.root / "link.qtab")
        self.good = CELL_POLICY.read_bytes()
        self.storage.write_atomic(ACTIVE_POLICY, self.good)
        self.key = random.Random(seed).randbytes(32)
        key_file = sandbox / "robot.key"
        key_file.write_text(self.key.hex())
        self.ctrl = Controller(None, load_policy(self.storage.resolve(ACTIVE_POLICY)))
        self.ftp = FtpServer(self.storage, activate=self.ctrl.activate_policy)
        self.node = MavNode(self.ctrl, ParamStore(self.root), Signing(self.root),
                            reboot_hook=self._reload_policy, ftp=self.ftp)
        self.node.boot(0, key_file)
        m = _dialect()
        self.parser = m.MAVLink(None, 1, 1)  # as MavShell sets up its connection's parser
        self.parser.robust_parsing = True
        self.parser.signing.secret_key = self.key
        self.parser.signing.allow_unsigned_callback = lambda _mav, _msg_id: True
        self.now_us = 1_000_000
        self.outside = _outside_snapshot(sandbox, self.root)
        self.load_policy = load_policy

    def _reload_policy(self) -> tuple[bool, str]:
        from firmware_py.policy import PolicyError
        from firmware_py.storage import boot_policy_candidates

        for path in boot_policy_candidates(self.storage):
            try:
                return self.ctrl.activate_loaded(self.load_policy(path))
            except PolicyError:
                continue
        return False, "no valid policy in storage"

    def feed(self, data: bytes) -> list:
        """Parse like the shell and handle; returns [(msg, replies)]."""
        out = []
        for msg in self.parser.parse_buffer(data) or []:
            self.now_us += 1000
            out.append((msg, self.node.handle(msg, self.now_us)))
        return out

    def tick(self) -> None:
        self.now_us += 1000
        self.node.tick(self.now_us)

    def policy_consistent(self) -> str:
        from firmware_py.policy import PolicyError
        from firmware_py.storage import ACTIVE_POLICY

        try:
            on_disk = self.load_policy(self.storage.resolve(ACTIVE_POLICY))
        except (PolicyError, OSError) as exc:
            return f"active.qtab does not load: {exc}"
        if self.ctrl.policy is None or self.ctrl.policy.crc != on_disk.crc:
            return "the controller runs a policy other than active.qtab"
        return ""

    def policy_consistent_on_disk(self) -> str:
        """After a run in another process: active.qtab (if any) loads."""
        from firmware_py.policy import PolicyError
        from firmware_py.storage import ACTIVE_POLICY

        try:
            self.load_policy(self.storage.resolve(ACTIVE_POLICY))
        except (PolicyError, OSError) as exc:
            return f"active.qtab does not load: {exc}"
        return ""

    def params_problems(self) -> list[str]:
        from firmware_py.mavlink.params import PARAMS, ParamStore

        out = [f"{d.name}={self.node.params.get(d.name)} outside [{d.min}, {d.max}]"
               for d in PARAMS if not d.readonly and not d.min <= self.node.params.get(d.name) <= d.max]
        out += [f"stored params: {w}" for w in ParamStore(self.root).load()]
        return out

    def outside_changed(self) -> list[str]:
        now = _outside_snapshot(self.sandbox, self.root)
        changed = sorted(set(now.items()) ^ set(self.outside.items()))
        return [f"outside the root changed: {p}" for p, _ in changed[:3]]


def _expected_drop(rig: HostileRig, kind: str, msg) -> str | None:
    """Counter that must rise for this frame, if it parsed into its message."""
    if kind == "unsigned" and msg.get_msgId() != 109 and rig.node.signing.require:
        return "dropped_unsigned"
    if kind == "badsig":
        return "dropped_badsig"
    if kind == "replay":
        return "dropped_replay"
    return None


@register("mav_hostile_core", small=3000, large=100_000, unit="frames",
          what="random/mutated/unsigned/replayed frames into the node core: no crash, nothing outside the root")
def hostile_core(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    from firmware_py.mavlink.params import PARAMS

    kinds: dict[str, int] = {}
    ranges = {d.name: (d.min, d.max) for d in PARAMS}
    with tempfile.TemporaryDirectory(prefix="qnav-hostile-") as tmp:
        rig = HostileRig(Path(tmp), seed)
        maker = FrameMaker(random.Random(seed), rig.key, rig.good)
        sig = rig.node.signing
        block_bad: list[str] = []
        for i in trials(count, progress):
            kind, data, msg = maker.next()
            kinds[kind] = kinds.get(kind, 0) + 1
            problems: list[str] = []
            before = {k: getattr(sig, k) for k in ("dropped_unsigned", "dropped_badsig", "dropped_replay")}
            policy_before = rig.ctrl.policy
            try:
                handled = rig.feed(data)
                if i % 50 == 49:
                    rig.tick()
            except Exception as exc:  # the robot would have crashed here
                problems.append(f"{type(exc).__name__}: {exc}")
                handled = []
            parsed = [(mm, r) for mm, r in handled if msg is not None and mm.get_msgId() == msg.get_msgId()]
            if parsed and (counter := _expected_drop(rig, kind, msg)) and getattr(sig, counter) <= before[counter]:
                problems.append(f"{kind} {msg.get_type()} not dropped by {counter}")
            for mm, replies in handled:
                t = mm.get_type()
                if t == "PARAM_SET" and mm.param_id in ranges:
                    lo, hi = ranges[mm.param_id]
                    if not lo <= rig.node.params.get(mm.param_id) <= hi:
                        problems.append(f"PARAM_SET left {mm.param_id}={rig.node.params.get(mm.param_id)}")
                if (t == "FILE_TRANSFER_PROTOCOL" and kind == "signed" and mm.target_system in (0, 1)
                        and mm.target_component in (0, 1) and mm.payload[3] not in (128, 129) and not replies):
                    problems.append(f"signed FTP request opcode {mm.payload[3]} got no answer")
            if rig.ctrl.policy is not policy_before and (why := rig.policy_consistent()):
                problems.append(why)
            if i % 500 == 499 or i == count - 1:
                block_bad = rig.outside_changed() + rig.params_problems()
                if (why := rig.policy_consistent()):
                    block_bad.append(why)
                problems += block_bad
            res.check(problems, f"frame {i} ({kind})")
        st, fs = rig.node.stats, rig.ftp.stats
        res.figures.update({
            "frames_by_kind": kinds, "rx_messages": st.rx_total, "rx_dropped": st.rx_dropped,
            "dropped_unsigned": sig.dropped_unsigned, "dropped_badsig": sig.dropped_badsig,
            "dropped_replay": sig.dropped_replay, "parser_errors": rig.parser.total_receive_errors,
            "ftp_requests": fs.requests, "ftp_naks": fs.naks, "ftp_malformed": fs.malformed,
            "ftp_activations": fs.activations, "ftp_refusals": fs.refusals,
            "reboots": rig.node.reboots})


def _answers_param(link, name: str, tries: int = 5) -> bool:
    """A PARAM_REQUEST_READ answered (other traffic in between is skipped)."""
    for _ in range(tries):
        link.conn.mav.param_request_read_send(link.sysid, link.compid, name.encode(), -1)
        if link.recv("PARAM_VALUE", 1.0, cond=lambda p: p.param_id == name) is not None:
            return True
    return False


@register("mav_hostile_udp", small=1500, large=20_000, unit="frames over UDP to qnav-robot",
          what="the same frames to a running qnav-robot: it keeps answering, counts drops, root kept")
def hostile_udp(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    """The real transport once: a `qnav-robot` process (signing on) gets the
    frames on its UDP port from a signed ground-station link; afterwards it
    must still be running and answering, report drops in SYS_STATUS, and have
    changed nothing outside its storage root. Only the end state is visible
    over UDP, so the run is all survived or all lost."""
    import time

    from ground_station.mavlink.link import Link, LinkError

    with tempfile.TemporaryDirectory(prefix="qnav-hostile-udp-") as tmp:
        sandbox = Path(tmp) / "sandbox"
        rig = HostileRig(sandbox, seed)  # builds the sandbox, root, symlinks, key and policy
        key_file = sandbox / "robot.key"
        maker = FrameMaker(random.Random(seed), rig.key, rig.good)
        problems: list[str] = []
        with RobotProcess(rig.root, key_file=key_file, log=Path(tmp) / "robot.log") as robot:
            link = Link(robot.url, signing_key=key_file, tlog=False)
            try:
                link.connect(20.0)
                t0 = time.monotonic()
                for i in trials(count, progress):
                    link.conn.write(maker.next()[1])
                    if i % 50 == 49:
                        time.sleep(0.02)  # ~2500 frames/s: what one control tick's poll takes in
                        while link.conn.recv_match(blocking=False) is not None:
                            pass
                res.figures["send_seconds"] = time.monotonic() - t0
                time.sleep(0.5)
                if not robot.alive:
                    problems.append(f"qnav-robot died: {robot.log_tail()}")
                else:
                    if not _answers_param(link, "SYSID_THISMAV"):
                        problems.append("no PARAM_VALUE answer after the flood")
                    st = link.recv("SYS_STATUS", timeout_s=5.0)
                    if st is None:
                        problems.append("no SYS_STATUS after the flood")
                    else:
                        res.figures.update({"robot_rx_dropped": st.errors_comm,
                                            "robot_signing_dropped": st.errors_count3})
                        if st.errors_comm == 0 or st.errors_count3 == 0:
                            problems.append(f"drops not counted: SYS_STATUS {st}")
            except LinkError as exc:
                problems.append(f"robot stopped answering: {exc}")
            finally:
                link.close()
            code = robot.stop()
            if code not in (0, 130):
                problems.append(f"qnav-robot exit code {code}: {robot.log_tail()}")
        problems += rig.outside_changed() + rig.params_problems()
        if (why := rig.policy_consistent_on_disk()):
            problems.append(why)
        res.tried = count
        res.survived = count if not problems else 0
        res.failures = problems[:20]
