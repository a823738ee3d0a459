"""`qnav upload FILE [--activate] --mavlink URL`: put a policy on the robot
with pymavlink's own MAVLink FTP client, prove it arrived byte-exact, and
optionally activate it.

Steps (docs/mavlink.md, "Uploading a policy"):
1. RemoveFile of the remote name (a stale file there could pass step 3), then
   `MAVFTP.cmd_put` to /policies/<name> (temporary name on the robot until the
   FTP session ends), with a progress bar;
2. `CalcFileCRC32` on the robot == FTP CRC32 of the local file, else the
   whole put is repeated (a lossy link can eat the CreateFile or the
   TerminateSession, which pymavlink's client never retries);
3. with --activate: FTP Rename onto /policies/active.qtab; the robot
   validates the file and refuses with NAK + STATUSTEXT reason (exit 3);
4. the verdict comes from the robot's state, never from one reply: done only
   when the robot reports the file's POLICY_ID and POLICY_CRC_HI/LO
   parameters AND CalcFileCRC32 of active.qtab equals the local CRC. A lost
   reply or read is asked again within the time budget; while the uploaded
   file is still under its own name the rename did not happen and is sent
   again. (The whole-file CRC alone cannot tell two policies apart: every
   valid .qtab of one size has the same one, the file ending in its own
   CRC32.) A robot that serves no parameters (the standalone FTP shell: its
   HEARTBEAT reports no system state) is confirmed by the rename's ACK or the
   file having left its name, plus the CRC of active.qtab, and says so.

The put keeps pymavlink's 80-byte writes; `WriteGate` gives it a real
in-flight window (10 writes) and spaces copies of a write by the measured
round trip, so a lossy radio's queue never fills with re-sends, and the put
counts as done only when every block was ACKed.

Every FTP reply is matched by the request's own seq. One MAVFTP client serves
a RobotLink for its whole life, so seq never restarts and a late reply to an
earlier request (a lossy radio queues seconds of them) cannot answer a later
one.

Exit status: 0 done, 2 bad arguments, 3 refused by the robot, 4 timeout or
no robot, 5 CRC or policy-id mismatch.
"""

from __future__ import annotations

import argparse
import os
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path

from ground_station.errors import CliError

EXIT_REFUSED, EXIT_TIMEOUT, EXIT_MISMATCH = 3, 4, 5
ACTIVE_POLICY = "/policies/active.qtab"  # firmware_py.storage.ACTIVE_POLICY; imported lazily below
GCS_SYSID, GCS_COMPID = 255, 190  # MAV_COMP_ID_MISSIONPLANNER, as ground stations use
POLICY_PARAMS = ("POLICY_ID", "POLICY_CRC_HI", "POLICY_CRC_LO")
MAV_STATE_UNINIT = 0
NAK_FAIL, NAK_FAIL_ERRNO, NAK_FILE_NOT_FOUND = 1, 2, 10
ENOENT = 2
PARAM_ASK_INTERVAL_S = 0.5  # re-ask an unanswered PARAM_REQUEST_READ after this long
READ_BUDGET_S = 10.0  # one round of reads (params, CRC) before the caller looks again
# MAVFTP sends another write when none was ACKed for max(min(10 x rtt, 1 s), 0.2 s), rtt being
# the smallest round trip it saw (0.5 s until then): at 40 % loss its 5 writes in flight are
# often all lost and it then adds one write per 0.5 s. With WriteGate keeping the real window
# and spacing copies, the put lets it re-send after 0.2 s and count 10 in flight.
EAGER_RTT_S = 0.02
PUT_QSIZE = 10


class UploadFailed(Exception):
    """The upload did not complete; `code` is the exit status."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass
class UploadResult:
    remote: str
    size: int
    crc: int
    put_attempts: int = 0
    put_seconds: float = 0.0  # first FTP request to CRC verified
    activated: bool = False
    confirmed_by: str = ""
    policy_id: int | None = None  # from the local file, when it loads
    policy_crc: int | None = None  # the .qtab's own CRC32 (what POLICY_CRC reports)
    local_error: str = ""  # why the local loader refused the file, if it did
    renames: int = 0  # Rename requests sent
    texts: list[str] = field(default_factory=list)

    def want_params(self) -> dict[str, float] | None:
        """What the robot's POLICY_* parameters read once this file runs."""
        if self.policy_id is None or self.policy_crc is None:
            return None
        return {"POLICY_ID": _float32(self.policy_id), "POLICY_CRC_HI": float(self.policy_crc >> 16),
                "POLICY_CRC_LO": float(self.policy_crc & 0xFFFF)}


def _import_pymavlink():
    # Without MAVLINK20=1 pymavlink starts in MAVLink 1 and its later switch to
    # 2 throws away setup_signing() (design.md section 3).
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavftp, mavutil

    return mavutil, mavftp


class WriteGate:
    """A real in-flight window for MAVFTP's WriteFile requests: a write goes
    out only while fewer than `window` writes are unanswered and younger than
    the hold time, and a copy of a write (same session and seq) only once
    the previous copy's ACK is overdue. A held-back write counts for MAVFTP
    as sent; it tries the block again on a later round, and that try goes out
    when the window allows.

    Why: after its first pass, pymavlink's MAVFTP re-sends every unanswered
    block round-robin, and its own in-flight count treats each block index
    skipped between two ACKs as lost - in the sparse set of remaining blocks
    every ACK skips many - so it refills its window of 5 on every ACK and
    cycles the last blocks faster than their ACKs return. Measured at 20 %
    loss + duplication + reordering (20 KiB): up to 29 copies of one block
    and the radio queue at 3.4 s. A slot is free again once its write is
    answered or older than the hold, 1.5 x the smoothed round trip of writes
    sent once (Karn's rule), at least `min_hold_s`; 10 writes of 80 bytes are
    ~0.2 s of air at 57600 baud, so the radio queue stays below that. 100 KiB
    signed at 20 % loss + 10 % duplication/reordering: 53 s instead of 80 s,
    1.74 frames per block instead of 2.62. At 0 % loss the window is never
    full and the put runs at the link rate, as before. (A hold of 2.5 x SRTT
    and a window of 5 left the link idle in the tail at 40 % loss.) """

    def __init__(self, conn, opcode_write: int, window: int = 10, min_hold_s: float = 0.15) -> None:
        self.opcode_write, self.window, self.min_hold_s = opcode_write, window, min_hold_s
        self.sent: dict[tuple[int, int], tuple[float, int]] = {}  # (session, seq) -> (last sent, copies)
        self.srtt: float | None = None
        self.held = self.passed = 0
        self._send = conn.mav.file_transfer_protocol_send
        conn.mav.file_transfer_protocol_send = self.send

    def hold_s(self) -> float:
        return max(self.min_hold_s, 1.5 * self.srtt) if self.srtt is not None else 1.0

    def send(self, network, target_system, target_component, payload, *args, **kwargs):
        seq, session, opcode = struct.unpack_from("<HBB", bytes(payload[:4]), 0)
        if opcode == self.opcode_write:
            now, hold = time.monotonic(), self.hold_s()
            last, copies = self.sent.get((session, seq), (None, 0))
            in_flight = sum(1 for t, _ in self.sent.values() if now - t < hold)
            if (last is not None and now - last < hold) or in_flight >= self.window:
                self.held += 1
                return None
            self.sent[(session, seq)] = (now, copies + 1)
            self.passed += 1
        elif opcode in (1, 2):  # TerminateSession, ResetSessions: the put's writes are over
            self.sent.clear()
        return self._send(network, target_system, target_component, payload, *args, **kwargs)

    def acked(self, session: int, reply_seq: int) -> None:
        """A WriteFile reply arrived: frees its slot; a round-trip sample if one copy went out."""
        got = self.sent.pop((session, (reply_seq - 1) % 65536), None)
        if got is not None and got[1] == 1:
            rtt = time.monotonic() - got[0]
            self.srtt = rtt if self.srtt is None else 0.875 * self.srtt + 0.125 * rtt


class RobotLink:
    """A pymavlink connection to the robot plus what we overhear on it."""

    def __init__(self, url: str, signing_key: bytes | None = None, timeout_s: float = 10.0,
                 conn=None) -> None:
        """`conn`: an open pymavlink connection to share (signing already set
        up on it), e.g. `ground_station.mavlink.link.Link.conn`; else one is opened on `url`."""
        mavutil, self.mavftp = _import_pymavlink()
        shared = conn is not None
        self.conn = conn if shared else mavutil.mavlink_connection(
            url, source_system=GCS_SYSID, source_component=GCS_COMPID)
        if signing_key is not None and not shared:
            self.conn.setup_signing(signing_key, sign_outgoing=True, allow_unsigned_callback=None)
        self.gate = WriteGate(self.conn, self.mavftp.OP_WriteFile)
        # (req_opcode, reply seq) -> (opcode, data); seq never restarts (one MAVFTP client)
        self.ftp_replies: dict[tuple[int, int], tuple[int, bytes]] = {}
        self.texts: list[str] = []
        self.params: dict[str, tuple[float, float]] = {}  # name -> (value, monotonic time received)
        self.param_values_seen = 0
        self.system_status: int | None = None  # the robot's HEARTBEAT system_status
        self._ftp = None
        self.conn.message_hooks.append(self._hook)
        self.target_system, self.target_component = self._wait_heartbeat(timeout_s)

    def _hook(self, _conn, msg) -> None:
        t = msg.get_type()
        if t == "FILE_TRANSFER_PROTOCOL":
            seq, session, opcode, size, req_opcode = struct.unpack_from("<HBBBB", bytes(msg.payload), 0)
            self.ftp_replies[(req_opcode, seq)] = (opcode, bytes(msg.payload[12:12 + size]))
            if req_opcode == self.mavftp.OP_WriteFile:
                self.gate.acked(session, seq)
        elif t == "STATUSTEXT":
            self.texts.append(msg.text)
        elif t == "PARAM_VALUE":
            self.params[msg.param_id] = (msg.param_value, time.monotonic())
            self.param_values_seen += 1
        elif t == "HEARTBEAT" and msg.get_srcSystem() != GCS_SYSID:
            self.system_status = msg.system_status

    def _wait_heartbeat(self, timeout_s: float) -> tuple[int, int]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            # our heartbeat lets a robot (or radio relay) that listens learn our address
            self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)  # MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID
            msg = self.conn.recv_match(type="HEARTBEAT", blocking=True, timeout=1.0)
            if msg is not None and msg.get_srcSystem() != GCS_SYSID:
                return msg.get_srcSystem(), msg.get_srcComponent()
        raise UploadFailed(EXIT_TIMEOUT, f"no HEARTBEAT from a robot within {timeout_s:.0f} s")

    @property
    def serves_params(self) -> bool:
        """The robot's node reports a system state in its HEARTBEAT and serves
        parameters (POLICY_* among them); the bare FTP shell reports
        MAV_STATE_UNINIT and serves none."""
        return self.param_values_seen > 0 or self.system_status not in (None, MAV_STATE_UNINIT)

    def ftp(self):
        """The link's one pymavlink MAVFTP client, made on first use.

        Its request seq counts on for the link's whole life, so a late or
        duplicated reply to an earlier request can never be matched to a later
        one. Its ResetSessions (sent when it is made) is not waited for: the
        first real request, asked until answered, tells whether the robot
        serves FTP at all."""
        if self._ftp is None:
            settings = self.mavftp.MAVFTPSettings(
                [(name, type(value), value) for name, value in DEFAULT_FTP_SETTINGS.items()])
            quick(settings)
            self._ftp = self.mavftp.MAVFTP(self.conn, self.target_system, self.target_component,
                                           settings=settings)
        return self._ftp

    def ask(self, ftp, command: str, args: list[str], opcode: int, wait_s: float, what: str) -> tuple[int, bytes]:
        """A single-reply MAVFTP request that may safely run twice (CRC,
        RemoveFile), sent again until the robot answers, for at most `wait_s`.
        Returns (opcode, data) of the newest answered copy; a late reply to an
        earlier copy counts too (they all ask the same question)."""
        deadline = time.monotonic() + wait_s
        seqs: list[int] = []
        while True:
            seqs.append(ftp.seq)  # MAVFTP sends with this seq and then counts on
            ftp.cmd_ftp([command, *args])
            for seq in reversed(seqs):
                reply = self.ftp_replies.get((opcode, (seq + 1) % 65536))
                if reply is not None:
                    return reply
            if time.monotonic() > deadline:
                raise UploadFailed(EXIT_TIMEOUT, f"no reply to {what} ({len(seqs)} requests in {wait_s:.0f} s)")

    def remote_crc(self, ftp, path: str, wait_s: float = 20.0) -> int | None:
        """CalcFileCRC32 of `path`, None if the robot has no such file."""
        opcode, data = self.ask(ftp, "crc", [path], self.mavftp.OP_CalcFileCRC32, wait_s, f"the CRC of {path}")
        if opcode == self.mavftp.OP_Ack and len(data) == 4:
            return struct.unpack("<I", data)[0]
        return None

    def read_params(self, names, budget_s: float = READ_BUDGET_S,
                    want: dict[str, float] | None = None) -> dict[str, float | None]:
        """Values of `names` the robot sent after this call began (None: not
        answered within `budget_s`). A name is asked again every
        PARAM_ASK_INTERVAL_S until answered - a lost PARAM_VALUE is only a
        retry - and, with `want`, until it equals its wanted value (the robot
        updates its read-only POLICY_* mirror on the next control tick).
        Returns as soon as every name is answered (and matches `want`)."""
        t0 = time.monotonic()
        end = t0 + budget_s
        asked: dict[str, float] = {}

        def fresh(name):
            got = self.params.get(name)
            return got[0] if got is not None and got[1] >= t0 else None

        def done(name):
            value = fresh(name)
            return value is not None and (want is None or value == want[name])

        while True:
            now = time.monotonic()
            for name in names:
                if not done(name) and now - asked.get(name, -1e9) >= PARAM_ASK_INTERVAL_S:
                    self.conn.mav.param_request_read_send(self.target_system, self.target_component,
                                                          name.encode(), -1)
                    asked[name] = now
            if all(done(n) for n in names) or now > end:
                return {n: fresh(n) for n in names}
            self.conn.recv_match(blocking=True, timeout=0.05)  # the hook records what arrives

    def read_param(self, name: str, tries: int = 3, timeout_s: float = 1.0) -> float | None:
        """One parameter's current value, asked for up to `tries` x `timeout_s`."""
        return self.read_params([name], budget_s=tries * timeout_s)[name]

    def close(self) -> None:
        self.conn.close()


# pymavlink MAVFTP's own defaults (mavftp.MAVFTP.__init__).
DEFAULT_FTP_SETTINGS = {"debug": 0, "pkt_loss_tx": 0, "pkt_loss_rx": 0, "max_backlog": 5,
                        "burst_read_size": 80, "write_size": 80, "write_qsize": 5,
                        "idle_detection_time": 3.7, "read_retry_time": 1.0, "retry_time": 0.5}


def quick(settings) -> None:
    """Single-reply operations (CRC, Rename, RemoveFile, TerminateSession)
    have no completion signal in MAVFTP: it waits `idle_detection_time` of
    silence after the reply. A 57600 link answers a short request in tens of ms, so wait 0.4 s
    instead of 3.7 s; a reply later than that counts as lost, the caller asks
    again and still accepts the late reply."""
    settings.read_retry_time = 0.3
    settings.idle_detection_time = 0.4


def for_put(settings) -> None:
    """The put: MAVFTP may keep PUT_QSIZE writes in flight by its own count
    (WriteGate holds the real number to its window, so a larger count only
    stops MAVFTP from stalling when its writes are lost). Idle time longer
    than MAVFTP's slowest write re-send (max(min(10 x RTT, 1 s), 0.2 s)
    without an ACK), so a put in progress never looks idle, and far below
    pymavlink's 3.7 s, which a put whose TerminateSession reply was lost (or a
    NAKed put) waits out in full."""
    settings.write_qsize = PUT_QSIZE
    settings.read_retry_time = 0.3
    settings.idle_detection_time = 1.5


def _float32(value: int) -> float:
    """What a PARAM_VALUE carries for an integer parameter (C cast to float32)."""
    return struct.unpack("<f", struct.pack("<f", float(value)))[0]


def _left(deadline: float) -> float:
    return max(0.0, deadline - time.monotonic())


def upload_policy(link: RobotLink, local: Path, remote: str, *, activate: bool = False,
                  deadline_s: float = 300.0, attempts: int = 8, progress=None) -> UploadResult:
    """Put `local` at `remote` on the robot, verify its CRC, optionally activate.

    Raises UploadFailed. `progress(fraction)` is called during the put.
    """
    from firmware_py.policy import PolicyError, load_policy
    from firmware_py.storage import ftp_crc32

    data = local.read_bytes()
    res = UploadResult(remote=remote, size=len(data), crc=ftp_crc32(data))
    try:
        pol = load_policy(data)
        res.policy_id, res.policy_crc = pol.policy_id, pol.crc
    except PolicyError as exc:
        res.local_error = str(exc)  # not a policy this build can load: the robot will judge it
    deadline = time.monotonic() + deadline_s
    t0 = time.monotonic()
    ftp = link.ftp()
    _put_verified(link, ftp, local, res, deadline, attempts, progress)
    res.put_seconds = time.monotonic() - t0
    if activate:
        _activate(link, ftp, res, deadline, deadline_s)
        res.texts = list(link.texts)
    return res


def _put_verified(link: RobotLink, ftp, local: Path, res: UploadResult, deadline: float, attempts: int,
                  progress) -> None:
    """Put until CalcFileCRC32 of `res.remote` equals the local CRC."""
    mavftp = link.mavftp
    remote = res.remote
    # A file already under this name could pass the CRC check without the put
    # (same size -> same whole-file CRC for any valid .qtab): remove it first.
    # Its answer is also the first sign that the robot serves FTP to us.
    wait = min(15.0, max(2.0, _left(deadline)))
    try:
        opcode, data = link.ask(ftp, "rm", [remote], mavftp.OP_RemoveFile, wait, f"RemoveFile {remote}")
    except UploadFailed as exc:
        raise UploadFailed(EXIT_TIMEOUT, f"the robot does not answer MAVLink FTP ({exc}; wrong or missing "
                                         f"--signing-key?)") from None
    absent = data[:1] == bytes([NAK_FILE_NOT_FOUND]) or data[:2] == bytes([NAK_FAIL_ERRNO, ENOENT])
    if opcode != mavftp.OP_Ack and not absent:
        code = data[0] if data else 0
        raise UploadFailed(EXIT_REFUSED, f"robot refuses to replace {remote} (FTP NAK {code})")
    problem = "no put attempted"
    for attempt in range(1, attempts + 1):
        if time.monotonic() > deadline:
            raise UploadFailed(EXIT_TIMEOUT, f"{remote} not verified in time ({problem})")
        res.put_attempts = attempt
        if ftp.write_list is not None:  # a put still open in the client: end it first
            ftp.cmd_cancel()
        put_session = ftp.session  # the robot numbers the session as we do
        for_put(ftp.ftp_settings)
        ftp.rtt = min(ftp.rtt, EAGER_RTT_S)
        ftp.cmd_put([str(local), remote], progress_callback=progress)
        # process_ftp_reply also returns after idle_detection_time without a
        # send, reporting the last reply it handled: "Success" then only means
        # the last ACK was one. The put is done when every block is ACKed
        # (MAVFTP then ends the session itself); while blocks are left, go on.
        ret = None
        while ftp.write_list is not None and time.monotonic() < deadline:
            ret = ftp.process_ftp_reply("put", timeout=max(10.0, _left(deadline)))
        quick(ftp.ftp_settings)
        if ftp.write_list is not None:  # out of time in the middle of the put
            ftp.cmd_cancel()
            raise UploadFailed(EXIT_TIMEOUT, f"{remote}: put not finished within the time budget "
                                             f"({ftp.write_acks} of {ftp.write_total} blocks acknowledged)")
        if ftp.write_acks < ftp.write_total:
            # NAKed (e.g. WriteFile InvalidSession after a lost CreateFile): MAVFTP
            # ended the session, the robot has a partial file at most -> put again
            code = getattr(ret.error_code, "name", ret.error_code) if ret is not None else "?"
            problem = f"put attempt {attempt} ended by {code} after {ftp.write_acks} of {ftp.write_total} blocks"
            continue
        wait = min(20.0, max(2.0, _left(deadline)))
        crc = link.remote_crc(ftp, remote, wait)
        if crc is None:
            # Every block ACKed but no file: only the TerminateSession was lost
            # (pymavlink never repeats it), so the data waits under a temporary
            # name until the session expires. End that session again, look again.
            ftp.session = put_session
            ftp.cmd_cancel()
            crc = link.remote_crc(ftp, remote, wait)
        if crc == res.crc:
            return
        problem = "missing on the robot" if crc is None else f"robot CRC32 0x{crc:08x} != local 0x{res.crc:08x}"
    code = EXIT_MISMATCH if problem.startswith("robot CRC32") else EXIT_TIMEOUT
    raise UploadFailed(code, f"{remote} not verified after {attempts} puts ({problem})")


def _activate(link: RobotLink, ftp, res: UploadResult, deadline: float, deadline_s: float) -> None:
    """Rename the verified file onto active.qtab until the robot's state shows
    it active (see the module docstring, step 4). Replies only steer: a NAK
    Fail is the robot's refusal; an ACK or a lost reply is checked against
    what the robot reports."""
    mavftp = link.mavftp
    want = res.want_params()
    params = link.serves_params
    if params and want is None:
        _activate_unreadable(link, ftp, res, deadline, deadline_s)  # always raises
    rename_seqs: list[int] = []
    texts_from = len(link.texts)
    status = "no reply yet"
    send_rename = True
    while True:
        if time.monotonic() > deadline:
            raise UploadFailed(EXIT_TIMEOUT, f"activation not confirmed within {deadline_s:.0f} s ({status})")
        if send_rename:
            rename_seqs.append(ftp.seq)
            res.renames += 1
            ftp.cmd_ftp(["rename", res.remote, ACTIVE_POLICY])
            send_rename = False
        replies = [r for s in rename_seqs if (r := link.ftp_replies.get((mavftp.OP_Rename, (s + 1) % 65536)))]
        acked = any(op == mavftp.OP_Ack for op, _ in replies)
        refused = any(op == mavftp.OP_Nack and data[:1] == bytes([NAK_FAIL]) for op, data in replies)
        wait = min(READ_BUDGET_S, _left(deadline))

        if params:
            got = link.read_params(POLICY_PARAMS, wait)
            if None in got.values():
                status = f"robot reports {got}"
                continue  # reads lost: ask again
            if got == want:
                _confirm_crc(link, ftp, res, deadline, "POLICY_ID/POLICY_CRC params + active.qtab CRC32")
                return
        elif acked:
            _confirm_crc(link, ftp, res, deadline, "Rename ACK + active.qtab CRC32 (robot serves no parameters)")
            return
        if refused:
            _raise_refusal(link, texts_from, res.local_error)
        # Not (yet) the new policy. Still under its own name: the rename did not
        # happen (request or reply lost) -> send it again.
        remote_crc = link.remote_crc(ftp, res.remote, max(2.0, wait))
        if remote_crc == res.crc:
            status = f"{res.remote} still in place after {res.renames} rename(s)"
            send_rename = True
            continue
        # The file left its name: the robot renamed it. Its POLICY_* mirror
        # follows within a control tick.
        if not params:
            _confirm_crc(link, ftp, res, deadline, "file moved + active.qtab CRC32 (robot serves no parameters)")
            return
        got = link.read_params(POLICY_PARAMS, min(READ_BUDGET_S, _left(deadline)), want=want)
        if got == want:
            _confirm_crc(link, ftp, res, deadline, "POLICY_ID/POLICY_CRC params + active.qtab CRC32")
            return
        if None not in got.values():
            raise UploadFailed(EXIT_MISMATCH, f"{res.remote} was renamed but the robot reports "
                                              f"{_show(got)}, file has {_show(want)}")
        status = f"{res.remote} renamed, robot's policy parameters unanswered"


def _activate_unreadable(link: RobotLink, ftp, res: UploadResult, deadline: float, deadline_s: float) -> None:
    """Activation of a file our policy loader refuses (`res.local_error`): the
    robot still judges it - it runs the same loader, so its refusal (NAK Fail
    + STATUSTEXT reason, exit 3) is the expected end. Should it take the file
    anyway, its POLICY_* cannot be checked against a file we cannot read:
    exit 5. A lost reply is resolved as in `_activate`: while the file is
    still under its own name, the rename is sent again."""
    mavftp = link.mavftp
    rename_seqs: list[int] = []
    texts_from = len(link.texts)
    while time.monotonic() < deadline:
        rename_seqs.append(ftp.seq)
        res.renames += 1
        ftp.cmd_ftp(["rename", res.remote, ACTIVE_POLICY])
        replies = [r for s in rename_seqs if (r := link.ftp_replies.get((mavftp.OP_Rename, (s + 1) % 65536)))]
        if any(op == mavftp.OP_Nack and data[:1] == bytes([NAK_FAIL]) for op, data in replies):
            _raise_refusal(link, texts_from, res.local_error)
        wait = min(READ_BUDGET_S, max(2.0, _left(deadline)))
        if any(op == mavftp.OP_Ack for op, _ in replies) or link.remote_crc(ftp, res.remote, wait) != res.crc:
            raise UploadFailed(EXIT_MISMATCH, f"the robot took {res.remote}, but this ground station cannot "
                                              f"read it ({res.local_error}), so its POLICY_ID cannot confirm it")
    raise UploadFailed(EXIT_TIMEOUT, f"no answer to the activation within {deadline_s:.0f} s "
                                     f"(this ground station's loader: {res.local_error})")


def _confirm_crc(link: RobotLink, ftp, res: UploadResult, deadline: float, how: str) -> None:
    crc = link.remote_crc(ftp, ACTIVE_POLICY, min(20.0, max(2.0, _left(deadline))))
    if crc != res.crc:
        shown = "missing" if crc is None else f"0x{crc:08x}"
        raise UploadFailed(EXIT_MISMATCH, f"{ACTIVE_POLICY} CRC32 is {shown} after activation, "
                                          f"expected 0x{res.crc:08x}")
    res.activated = True
    res.confirmed_by = how


def _raise_refusal(link: RobotLink, texts_from: int, local_error: str = "") -> None:
    end = time.monotonic() + 1.0
    while time.monotonic() < end and not any("refused" in t for t in link.texts[texts_from:]):
        link.conn.recv_match(blocking=True, timeout=0.1)
    reasons = [t for t in link.texts[texts_from:] if "refused" in t]
    if reasons:
        raise UploadFailed(EXIT_REFUSED, reasons[-1])
    local = f"; this ground station's loader: {local_error}" if local_error else ""
    raise UploadFailed(EXIT_REFUSED, f"robot refused the policy (its reason lost{local})")


def _show(values: dict[str, float | None] | None) -> str:
    if values is None:
        return "unknown"
    return ", ".join(f"{k} {'?' if v is None else f'{v:.0f}'}" for k, v in values.items())


def default_remote(local: Path) -> str:
    name = local.name
    if f"/policies/{name}" in (ACTIVE_POLICY, "/policies/last_good.qtab"):
        name = f"upload-{name}"
    return f"/policies/{name}"


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("upload", help="upload a policy to the robot over MAVLink FTP (and activate it)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", type=Path, help="the .qtab policy file")
    p.add_argument("--mavlink", required=True,
                   help="pymavlink connection string, e.g. udpin:127.0.0.1:14550 or /dev/ttyUSB0,57600")
    p.add_argument("--activate", action="store_true", help="make it the robot's active policy")
    p.add_argument("--signing-key", type=Path, help="MAVLink 2 signing key file (32 bytes, 64 hex digits or a passphrase)")
    p.add_argument("--remote", help="path on the robot (default /policies/<file name>)")
    p.add_argument("--timeout", type=float, default=300.0, help="give up after this many seconds (default %(default)s)")
    p.add_argument("--attempts", type=int, default=8, help="whole-file put attempts (default %(default)s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from firmware_py.mavlink.signing import load_key_file

    if not args.file.is_file():
        raise CliError(f"{args.file}: no such file")
    key = None
    if args.signing_key is not None:
        try:
            key = load_key_file(args.signing_key)
        except ValueError as exc:
            raise CliError(str(exc)) from exc
    remote = args.remote or default_remote(args.file)
    size = args.file.stat().st_size
    try:
        link = RobotLink(args.mavlink, key, timeout_s=min(10.0, args.timeout))
    except UploadFailed as exc:
        print(f"qnav upload: error: {exc}", flush=True)
        return exc.code
    bar = tqdm(total=size, unit="B", unit_scale=True, desc=f"upload {args.file.name}")

    def progress(frac):
        if frac is not None:
            bar.n = int(frac * size)
            bar.refresh()

    try:
        res = upload_policy(link, args.file, remote, activate=args.activate, deadline_s=args.timeout,
                            attempts=args.attempts, progress=progress)
    except UploadFailed as exc:
        bar.close()
        print(f"qnav upload: error: {exc}", flush=True)
        return exc.code
    finally:
        link.close()
    bar.n = size
    bar.close()
    print(f"uploaded {args.file} -> {remote}: {res.size} B, CRC32 0x{res.crc:08x} verified on the robot, "
          f"{res.put_seconds:.1f} s, {res.put_attempts} attempt(s)")
    if args.activate:
        pid = f"0x{res.policy_id:08x}" if res.policy_id is not None else "unknown"
        print(f"activated: policy id {pid}, confirmed by {res.confirmed_by}")
    return 0
