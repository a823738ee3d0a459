"""Policy upload over MAVLink FTP on a `Link`: put a policy on the robot,
prove it arrived byte-exact, and optionally activate it (`upload_policy`).

The steps (RemoveFile, the put of `ftp_put.FtpPut`, CalcFileCRC32, the Rename onto
/policies/active.qtab) and why the verdict comes from the robot's state (POLICY_ID, POLICY_CRC_HI/LO
and the CRC of active.qtab), never from one reply: docs/mavlink.md, "Uploading a policy". Every FTP
reply is matched by its request's seq, from the link's one MAVFTP client (`FtpSession`), so a late
reply to an earlier request cannot answer a later one. Failures raise `LinkError` with the link's
exit codes: EXIT_REFUSED (3), EXIT_TIMEOUT (4), EXIT_MISMATCH (5).
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from firmware_py.mavlink.ftp_server import PAYLOAD_LEN, Nak
from firmware_py.mavlink.params import as_float32
from ground_station.mavlink import ftp_put
from ground_station.mavlink.ftp_put import FtpPut, PutStats
from ground_station.mavlink.link import (
    EXIT_MISMATCH,
    EXIT_REFUSED,
    EXIT_TIMEOUT,
    Link,
    LinkError,
    mavutil,
)

ACTIVE_POLICY = "/policies/active.qtab"  # firmware_py.storage.ACTIVE_POLICY; imported lazily below
POLICY_PARAMS = ("POLICY_ID", "POLICY_CRC_HI", "POLICY_CRC_LO")
NAK_FAIL, NAK_FAIL_ERRNO, NAK_FILE_NOT_FOUND = Nak.FAIL, Nak.FAIL_ERRNO, Nak.FILE_NOT_FOUND
ENOENT = 2
ERR_END_OF_FILE = 6  # MAVLink FTP NAK code: a listing or read past its end
READ_BUDGET_S = 10.0  # one round of reads (params, CRC) before the caller looks again


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
    writes_sent: int = 0  # WriteFile frames over all puts, copies included
    texts: list[str] = field(default_factory=list)

    def want_params(self) -> dict[str, float] | None:
        """What the robot's POLICY_* parameters read once this file runs."""
        if self.policy_id is None or self.policy_crc is None:
            return None
        return {"POLICY_ID": as_float32(self.policy_id), "POLICY_CRC_HI": float(self.policy_crc >> 16),
                "POLICY_CRC_LO": float(self.policy_crc & 0xFFFF)}


class FtpSession:
    """A link's one MAVFTP client, the shell that runs `ftp_put.FtpPut` and quick single requests,
    and every FTP reply overheard. Made by `ftp_session(link)`; the link must be connected."""

    def __init__(self, link: Link) -> None:
        mavutil()  # MAVLINK20 before pymavlink is imported
        from pymavlink import mavftp

        self.link = link
        self.mavftp = mavftp
        # (req_opcode, reply seq) -> (opcode, data); seq never restarts (one counter per link)
        self.replies: dict[tuple[int, int], tuple[int, bytes]] = {}
        self.listener: Callable[[bytes], None] | None = None  # the put in progress
        self.srtt: float | None = None  # from the last put: paces the single requests
        self.ask_rtt: float | None = None  # the last single request's round trip (seeds the put's)
        self.puts: list[PutStats] = []
        self._ftp: Any = None
        link.conn.message_hooks.append(self._hook)

    def _hook(self, _conn, msg) -> None:
        if msg.get_type() == "FILE_TRANSFER_PROTOCOL":
            payload = bytes(msg.payload)
            seq, _session, opcode, size, req_opcode = struct.unpack_from("<HBBBB", payload, 0)
            self.replies[(req_opcode, seq)] = (opcode, payload[12:12 + size])
            if self.listener is not None:
                self.listener(payload)

    def client(self):
        """The link's one pymavlink MAVFTP client, made on first use. Its ResetSessions is not
        waited for: the first real request, asked until answered, tells whether the robot serves FTP."""
        if self._ftp is None:
            settings = self.mavftp.MAVFTPSettings(
                [(name, type(value), value) for name, value in DEFAULT_FTP_SETTINGS.items()])
            quick(settings)
            self._ftp = self.mavftp.MAVFTP(self.link.conn, self.link.sysid, self.link.compid,
                                           settings=settings)
        return self._ftp

    def take_seq(self) -> int:
        ftp = self.client()
        seq = ftp.seq
        ftp.seq = (seq + 1) % 65536
        return seq

    def send(self, payload: bytes) -> None:
        """One FTP request payload to the robot (padded to the message's 251 bytes)."""
        padded = bytearray(payload) + bytearray(PAYLOAD_LEN - len(payload))
        self.link.conn.mav.file_transfer_protocol_send(0, self.link.sysid, self.link.compid, padded)

    def ask(self, opcode: int, data: bytes, wait_s: float, what: str, session: int = 0,
            offset: int = 0) -> tuple[int, bytes]:
        """A single-reply request that may safely run twice (CRC, RemoveFile): three copies at first
        (the robot's retry cache answers them), then again with a new seq after 3 x the put's
        smoothed RTT (0.3 s before any put), doubling up to 1 s, for at most `wait_s`. Returns
        (opcode, data) of the first answered copy, a late reply to an earlier one included."""
        deadline = time.monotonic() + wait_s
        seqs: list[int] = []
        rto = max(0.1, 3 * self.srtt) if self.srtt is not None else 0.3
        conn = self.link.conn
        sent_at: dict[int, float] = {}
        while True:
            seq = self.take_seq()
            seqs.append(seq)
            sent_at[seq] = time.monotonic()
            payload = ftp_put.request(seq, session, opcode, offset, data)
            self.send(payload)
            if len(seqs) == 1:  # a copy is a few ms of air; a timeout, 0.3 s
                self.send(payload)
                self.send(payload)
            until = min(deadline, time.monotonic() + rto)
            while True:
                for s in seqs:
                    reply = self.replies.get((opcode, (s + 1) % 65536))
                    if reply is not None:
                        self.ask_rtt = time.monotonic() - sent_at[s]  # each copy has its seq: exact
                        return reply
                left = until - time.monotonic()
                if left <= 0:
                    break
                conn.recv_match(type="FILE_TRANSFER_PROTOCOL", blocking=True, timeout=min(left, 0.05))
            if time.monotonic() >= deadline:
                raise LinkError(EXIT_TIMEOUT, f"no reply to {what} ({len(seqs)} requests in {wait_s:.0f} s)")
            rto = min(1.0, 2 * rto)

    def remote_crc(self, path: str, wait_s: float = 20.0) -> int | None:
        """CalcFileCRC32 of `path`, None if the robot has no such file."""
        opcode, data = self.ask(self.mavftp.OP_CalcFileCRC32, path.encode() + b"\0", wait_s,
                                f"the CRC of {path}")
        if opcode == self.mavftp.OP_Ack and len(data) == 4:
            return struct.unpack("<I", data)[0]
        return None

    def list_dir(self, path: str, wait_s: float = 10.0) -> list[tuple[str, int | None]] | None:
        """ListDirectory of `path`: [(name, size; None for a directory)], None if there is no such
        directory. Read in pages (each reply holds as many entries as fit) until the robot says EOF."""
        out: list[tuple[str, int | None]] = []
        while True:
            opcode, data = self.ask(self.mavftp.OP_ListDirectory, path.encode() + b"\0", wait_s,
                                    f"the listing of {path}", offset=len(out))
            if opcode != self.mavftp.OP_Ack:
                eof = data[:1] == bytes([ERR_END_OF_FILE])
                return out if eof or out else None
            entries = [e for e in data.split(b"\0") if e]
            if not entries:
                return out
            for e in entries:
                kind, text = e[:1], e[1:].decode(errors="replace")
                if kind == b"F":
                    name, _, size = text.partition("\t")
                    out.append((name, int(size) if size.isdigit() else 0))
                elif kind == b"D":
                    out.append((text, None))
                else:  # "S": skipped (an entry the server would not describe)
                    out.append((text, -1))

    def put(self, data: bytes, remote: str, deadline: float,
            progress: Callable[[float | None], None] | None = None) -> FtpPut:
        """Run one `FtpPut` of `data` to `remote` until done, failed or the deadline."""
        ftp = self.client()
        put = FtpPut(data, remote, session=ftp.session, seq=ftp.seq, ctrl_rtt=self.ask_rtt)
        conn = self.link.conn
        self.listener = lambda payload: put.on_reply(payload, time.monotonic())
        shown = -1
        try:
            while not put.finished:
                now = time.monotonic()
                if now > deadline:
                    break
                for payload in put.poll(now):
                    self.send(payload)
                ftp.seq = put.seq
                wake = put.wake_at()
                wait = 0.05 if wake is None else min(0.05, max(0.001, wake - time.monotonic()))
                conn.recv_match(type="FILE_TRANSFER_PROTOCOL", blocking=True, timeout=wait)
                if progress is not None and len(put.acked) != shown:
                    shown = len(put.acked)
                    progress(shown / put.n_blocks)
            for payload in put.poll(time.monotonic()):  # e.g. closing a session opened ahead
                self.send(payload)
        finally:
            self.listener = None
            ftp.seq = put.seq
            if put.srtt is not None:
                self.srtt = put.srtt
            self.puts.append(put.stats)
        return put


def ftp_session(link: Link) -> FtpSession:
    """The link's one FTP session, made on first use."""
    if link.ftp_session is None:
        link.ftp_session = FtpSession(link)
    return link.ftp_session


# pymavlink MAVFTP's own defaults (mavftp.MAVFTP.__init__).
DEFAULT_FTP_SETTINGS = {"debug": 0, "pkt_loss_tx": 0, "pkt_loss_rx": 0, "max_backlog": 5,
                        "burst_read_size": 80, "write_size": 80, "write_qsize": 5,
                        "idle_detection_time": 3.7, "read_retry_time": 1.0, "retry_time": 0.5}


def quick(settings) -> None:
    """MAVFTP ends a single-reply operation (CRC, Rename, RemoveFile) after `idle_detection_time`
    of silence: 0.4 s instead of 3.7 s (a 57600 link answers in tens of ms); a later reply counts
    as lost, the caller asks again and still accepts it."""
    settings.read_retry_time = 0.3
    settings.idle_detection_time = 0.4


def _left(deadline: float) -> float:
    return max(0.0, deadline - time.monotonic())


def upload_policy(link: Link, local: Path, remote: str, *, activate: bool = False,
                  deadline_s: float = 300.0, attempts: int = 8,
                  progress: Callable[[float | None], None] | None = None) -> UploadResult:
    """Put `local` at `remote` over the connected `link`, verify its CRC, optionally activate.
    Raises LinkError (exit codes 3, 4, 5); `progress(fraction)` is called during the put."""
    from firmware_py.policy import PolicyError, load_policy

    deadline = time.monotonic() + deadline_s
    res = _put_file(link, local, remote, deadline, attempts, progress)
    try:
        pol = load_policy(local.read_bytes())
        res.policy_id, res.policy_crc = pol.policy_id, pol.crc
    except PolicyError as exc:
        res.local_error = str(exc)  # not a policy this build can load: the robot will judge it
    if activate:
        _activate(ftp_session(link), res, deadline, deadline_s)
        res.texts = list(link.texts)
    return res


ACTIVE_MAP = "/maps/active.map"  # firmware_py.storage.ACTIVE_MAP
MAP_UPLOAD = "/maps/upload.map"


def upload_map(link: Link, local: Path, *, deadline_s: float = 120.0, attempts: int = 8) -> UploadResult:
    """Put a MovingAI map at /maps/upload.map, verify its CRC, then rename it onto /maps/active.map:
    the robot parses it with its own cell size, checks it against its policy, builds its localiser
    and answers the rename (ACK: active; NAK: refused, the reason in a STATUSTEXT, the old map kept).
    A lost reply is settled by the CRC of /maps/active.map. Raises LinkError (exit codes 3, 4, 5)."""
    deadline = time.monotonic() + deadline_s
    res = _put_file(link, local, MAP_UPLOAD, deadline, attempts)
    session = ftp_session(link)
    mavftp = session.mavftp
    texts_from = len(link.texts)
    while True:
        if time.monotonic() > deadline:
            raise LinkError(EXIT_TIMEOUT, f"map activation not confirmed within {deadline_s:.0f} s")
        res.renames += 1
        opcode, reply = session.ask(mavftp.OP_Rename, MAP_UPLOAD.encode() + b"\0" + ACTIVE_MAP.encode() + b"\0",
                                    min(30.0, max(2.0, _left(deadline))), f"Rename {MAP_UPLOAD} -> {ACTIVE_MAP}")
        if opcode == mavftp.OP_Ack:
            _confirm_crc(session, res, deadline, "Rename ACK + active.map CRC32", ACTIVE_MAP)
            res.texts = list(link.texts)
            return res
        if reply[:1] == bytes([NAK_FAIL]):
            _raise_refusal(link, texts_from, what="map")
        # no such file any more (an earlier copy was renamed and its ACK lost): the CRC settles it
        if session.remote_crc(ACTIVE_MAP, min(10.0, max(2.0, _left(deadline)))) == res.crc:
            res.activated, res.confirmed_by = True, "active.map CRC32 (the rename's reply was lost)"
            res.texts = list(link.texts)
            return res


def put_plain_file(link: Link, local: Path, remote: str, *, deadline_s: float = 60.0, attempts: int = 4) -> UploadResult:
    """Put a plain file (no activation: the targets beside the robot's map), verified by its CRC32."""
    return _put_file(link, local, remote, time.monotonic() + deadline_s, attempts)


def _put_file(link: Link, local: Path, remote: str, deadline: float, attempts: int,
              progress: Callable[[float | None], None] | None = None) -> UploadResult:
    """`local` put at `remote` and verified (`_put_verified`), its time in `put_seconds`."""
    from firmware_py.storage import ftp_crc32

    data = local.read_bytes()
    res = UploadResult(remote=remote, size=len(data), crc=ftp_crc32(data))
    t0 = time.monotonic()
    _put_verified(ftp_session(link), local, res, deadline, attempts, progress)
    res.put_seconds = time.monotonic() - t0
    return res


def _put_verified(session: FtpSession, local: Path, res: UploadResult, deadline: float, attempts: int,
                  progress) -> None:
    """Put until CalcFileCRC32 of `res.remote` equals the local CRC."""
    mavftp = session.mavftp
    remote = res.remote
    # A file already under this name could pass the CRC check without the put
    # (same size -> same whole-file CRC for any valid .qtab): remove it first.
    # Its answer is also the first sign that the robot serves FTP to us.
    wait = min(15.0, max(2.0, _left(deadline)))
    try:
        opcode, data = session.ask(mavftp.OP_RemoveFile, remote.encode() + b"\0", wait, f"RemoveFile {remote}")
    except LinkError as exc:
        raise LinkError(EXIT_TIMEOUT, f"the robot does not answer MAVLink FTP ({exc}; wrong or missing "
                                         f"--signing-key?)") from None
    absent = data[:1] == bytes([NAK_FILE_NOT_FOUND]) or data[:2] == bytes([NAK_FAIL_ERRNO, ENOENT])
    if opcode != mavftp.OP_Ack and not absent:
        code = data[0] if data else 0
        raise LinkError(EXIT_REFUSED, f"robot refuses to replace {remote} (FTP NAK {code})")
    problem = "no put attempted"
    data = local.read_bytes()
    for attempt in range(1, attempts + 1):
        if time.monotonic() > deadline:
            raise LinkError(EXIT_TIMEOUT, f"{remote} not verified in time ({problem})")
        res.put_attempts = attempt
        put = session.put(data, remote, deadline, progress)
        res.writes_sent += put.stats.writes_sent
        if put.state == "failed":
            # NAKed: CreateFile refused (protected name, quota) is the robot's answer;
            # a WriteFile NAK (e.g. InvalidSession after the session expired) -> put again
            if put.error.startswith("CreateFile") and put.nak[:1] in (bytes([9]), bytes([2])):
                raise LinkError(EXIT_REFUSED, f"robot refuses to write {remote} ({put.error})")
            problem = f"put attempt {attempt} ended by {put.error} after {len(put.acked)} of {put.n_blocks} blocks"
            continue
        if not put.finished:
            raise LinkError(EXIT_TIMEOUT, f"{remote}: put not finished within the time budget "
                                             f"({len(put.acked)} of {put.n_blocks} blocks acknowledged)")
        if put.remote_crc == res.crc:  # the put's last answer: CalcFileCRC32 after the last commit
            return
        wait = min(20.0, max(2.0, _left(deadline)))
        crc = session.remote_crc(remote, wait)
        if crc == res.crc:
            return
        problem = "missing on the robot" if crc is None else f"robot CRC32 0x{crc:08x} != local 0x{res.crc:08x}"
    code = EXIT_MISMATCH if problem.startswith("robot CRC32") else EXIT_TIMEOUT
    raise LinkError(code, f"{remote} not verified after {attempts} puts ({problem})")


def _activate(session: FtpSession, res: UploadResult, deadline: float, deadline_s: float) -> None:
    """Rename the verified file onto active.qtab until the robot's state shows it active
    (docs/mavlink.md, "Uploading a policy", step 5). Replies only steer: a NAK Fail is the
    robot's refusal; an ACK or a lost reply is checked against what the robot reports."""
    link, mavftp, ftp = session.link, session.mavftp, session.client()
    want = res.want_params()
    params = link.serves_params
    if params and want is None:
        _activate_unreadable(session, res, deadline, deadline_s)  # always raises
    rename_seqs: list[int] = []
    texts_from = len(link.texts)
    status = "no reply yet"
    send_rename = True
    while True:
        if time.monotonic() > deadline:
            raise LinkError(EXIT_TIMEOUT, f"activation not confirmed within {deadline_s:.0f} s ({status})")
        if send_rename:
            rename_seqs.append(ftp.seq)
            res.renames += 1
            ftp.cmd_ftp(["rename", res.remote, ACTIVE_POLICY])
            send_rename = False
        replies = [r for s in rename_seqs if (r := session.replies.get((mavftp.OP_Rename, (s + 1) % 65536)))]
        acked = any(op == mavftp.OP_Ack for op, _ in replies)
        refused = any(op == mavftp.OP_Nack and data[:1] == bytes([NAK_FAIL]) for op, data in replies)
        wait = min(READ_BUDGET_S, _left(deadline))

        if params:
            got = link.read_params(POLICY_PARAMS, wait)
            if None in got.values():
                status = f"robot reports {got}"
                continue  # reads lost: ask again
            if got == want:
                _confirm_crc(session, res, deadline, "POLICY_ID/POLICY_CRC params + active.qtab CRC32")
                return
        elif acked:
            _confirm_crc(session, res, deadline, "Rename ACK + active.qtab CRC32 (robot serves no parameters)")
            return
        if refused:
            _raise_refusal(link, texts_from, res.local_error)
        # Still under its own name: the rename did not happen (request or reply lost): again.
        remote_crc = session.remote_crc(res.remote, max(2.0, wait))
        if remote_crc == res.crc:
            status = f"{res.remote} still in place after {res.renames} rename(s)"
            send_rename = True
            continue
        # The file left its name: renamed. Its POLICY_* mirror follows within a control tick.
        if not params:
            _confirm_crc(session, res, deadline, "file moved + active.qtab CRC32 (robot serves no parameters)")
            return
        got = link.read_params(POLICY_PARAMS, min(READ_BUDGET_S, _left(deadline)), want=want)
        if got == want:
            _confirm_crc(session, res, deadline, "POLICY_ID/POLICY_CRC params + active.qtab CRC32")
            return
        if None not in got.values():
            raise LinkError(EXIT_MISMATCH, f"{res.remote} was renamed but the robot reports "
                                              f"{_show(got)}, file has {_show(want)}")
        status = f"{res.remote} renamed, robot's policy parameters unanswered"


def _activate_unreadable(session: FtpSession, res: UploadResult, deadline: float, deadline_s: float) -> None:
    """Activation of a file our policy loader refuses (`res.local_error`): the robot runs the same
    loader, so its refusal (exit 3) is the expected end; should it take the file, its POLICY_*
    cannot be checked (exit 5). While the file is still under its own name, the rename is re-sent."""
    link, mavftp, ftp = session.link, session.mavftp, session.client()
    rename_seqs: list[int] = []
    texts_from = len(link.texts)
    while time.monotonic() < deadline:
        rename_seqs.append(ftp.seq)
        res.renames += 1
        ftp.cmd_ftp(["rename", res.remote, ACTIVE_POLICY])
        replies = [r for s in rename_seqs if (r := session.replies.get((mavftp.OP_Rename, (s + 1) % 65536)))]
        if any(op == mavftp.OP_Nack and data[:1] == bytes([NAK_FAIL]) for op, data in replies):
            _raise_refusal(link, texts_from, res.local_error)
        wait = min(READ_BUDGET_S, max(2.0, _left(deadline)))
        if any(op == mavftp.OP_Ack for op, _ in replies) or session.remote_crc(res.remote, wait) != res.crc:
            raise LinkError(EXIT_MISMATCH, f"the robot took {res.remote}, but this ground station cannot "
                                              f"read it ({res.local_error}), so its POLICY_ID cannot confirm it")
    raise LinkError(EXIT_TIMEOUT, f"no answer to the activation within {deadline_s:.0f} s "
                                     f"(this ground station's loader: {res.local_error})")


def _confirm_crc(session: FtpSession, res: UploadResult, deadline: float, how: str,
                 active: str = ACTIVE_POLICY) -> None:
    crc = session.remote_crc(active, min(20.0, max(2.0, _left(deadline))))
    if crc != res.crc:
        shown = "missing" if crc is None else f"0x{crc:08x}"
        raise LinkError(EXIT_MISMATCH, f"{active} CRC32 is {shown} after activation, "
                                          f"expected 0x{res.crc:08x}")
    res.activated = True
    res.confirmed_by = how


def _raise_refusal(link: Link, texts_from: int, local_error: str = "", what: str = "policy") -> None:
    end = time.monotonic() + 1.0
    while time.monotonic() < end and not any("refused" in t for t in link.texts[texts_from:]):
        link.conn.recv_match(blocking=True, timeout=0.1)
    reasons = [t for t in link.texts[texts_from:] if "refused" in t]
    if reasons:
        raise LinkError(EXIT_REFUSED, reasons[-1])
    local = f"; this ground station's loader: {local_error}" if local_error else ""
    raise LinkError(EXIT_REFUSED, f"robot refused the {what} (its reason lost{local})")


def _show(values: Mapping[str, float | None] | None) -> str:
    if values is None:
        return "unknown"
    return ", ".join(f"{k} {'?' if v is None else f'{v:.0f}'}" for k, v in values.items())


def default_remote(local: Path) -> str:
    """/policies/<file name>, renamed if that is one of the robot's own slots."""
    name = local.name
    if f"/policies/{name}" in (ACTIVE_POLICY, "/policies/last_good.qtab"):
        name = f"upload-{name}"
    return f"/policies/{name}"
