"""`qnav upload FILE [--activate] --mavlink URL`: put a policy on the robot
with pymavlink's own MAVLink FTP client, prove it arrived byte-exact, and
optionally activate it.

Steps (docs/mavlink.md, "Uploading a policy"):
1. `MAVFTP.cmd_put` to /policies/<name> (temporary name on the robot until the
   FTP session ends), with a progress bar;
2. `CalcFileCRC32` on the robot == FTP CRC32 of the local file, else the
   whole put is repeated (a lossy link can eat the CreateFile or the
   TerminateSession, which pymavlink's client never retries);
3. with --activate: FTP Rename onto /policies/active.qtab; the robot
   validates the file and refuses with NAK + STATUSTEXT reason (exit 3);
   a lost reply is resolved by asking the CRC of active.qtab;
4. confirm: the robot's read-only parameter POLICY_ID must equal the file's
   policy id; a robot that serves no parameters (the standalone FTP shell) is
   checked by the CRC of /policies/active.qtab instead, and says so.

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

from ground_station.cli import CliError

EXIT_REFUSED, EXIT_TIMEOUT, EXIT_MISMATCH = 3, 4, 5
ACTIVE_POLICY = "/policies/active.qtab"  # firmware_py.storage.ACTIVE_POLICY; imported lazily below
GCS_SYSID, GCS_COMPID = 255, 190  # MAV_COMP_ID_MISSIONPLANNER, as ground stations use


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
    put_seconds: float = 0.0  # first ResetSessions to CRC verified
    activated: bool = False
    confirmed_by: str = ""  # "POLICY_ID param" | "active.qtab CRC"
    policy_id: int | None = None  # from the local file, when it loads
    policy_crc: int | None = None  # the .qtab's own CRC32 (what POLICY_CRC reports)
    texts: list[str] = field(default_factory=list)


def _import_pymavlink():
    # Without MAVLINK20=1 pymavlink starts in MAVLink 1 and its later switch to
    # 2 throws away setup_signing() (design.md section 3).
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavftp, mavutil

    return mavutil, mavftp


class RobotLink:
    """A pymavlink connection to the robot plus what we overhear on it."""

    def __init__(self, url: str, signing_key: bytes | None = None, timeout_s: float = 10.0,
                 conn=None) -> None:
        """`conn`: an open pymavlink connection to share (signing already set
        up on it), e.g. `ground_station.link.Link.conn`; else one is opened on `url`."""
        mavutil, self.mavftp = _import_pymavlink()
        shared = conn is not None
        self.conn = conn if shared else mavutil.mavlink_connection(
            url, source_system=GCS_SYSID, source_component=GCS_COMPID)
        if signing_key is not None and not shared:
            self.conn.setup_signing(signing_key, sign_outgoing=True, allow_unsigned_callback=None)
        self.ftp_replies: dict[tuple[int, int], tuple[int, bytes]] = {}  # (req_opcode, seq) -> (opcode, data)
        self.texts: list[str] = []
        self.params: dict[str, object] = {}
        self.conn.message_hooks.append(self._hook)
        self.target_system, self.target_component = self._wait_heartbeat(timeout_s)

    def _hook(self, _conn, msg) -> None:
        t = msg.get_type()
        if t == "FILE_TRANSFER_PROTOCOL":
            seq, _session, opcode, size, req_opcode = struct.unpack_from("<HBBBB", bytes(msg.payload), 0)
            self.ftp_replies[(req_opcode, seq)] = (opcode, bytes(msg.payload[12:12 + size]))
        elif t == "STATUSTEXT":
            self.texts.append(msg.text)
        elif t == "PARAM_VALUE":
            self.params[msg.param_id] = msg

    def _wait_heartbeat(self, timeout_s: float) -> tuple[int, int]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            # our heartbeat lets a robot (or radio relay) that listens learn our address
            self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)  # MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID
            msg = self.conn.recv_match(type="HEARTBEAT", blocking=True, timeout=1.0)
            if msg is not None and msg.get_srcSystem() != GCS_SYSID:
                return msg.get_srcSystem(), msg.get_srcComponent()
        raise UploadFailed(EXIT_TIMEOUT, f"no HEARTBEAT from a robot within {timeout_s:.0f} s")

    def ftp(self, wait_s: float = 15.0):
        """A fresh pymavlink MAVFTP client whose ResetSessions the robot answered.

        Retried for `wait_s`: after a lossy put the radio's queue can hold
        seconds of retransmitted writes in front of our request."""
        deadline = time.monotonic() + wait_s
        tries = 0
        while True:
            tries += 1
            self.ftp_replies.clear()  # each client counts seq from 0 again
            settings = self.mavftp.MAVFTPSettings(
                [(name, type(value), value) for name, value in DEFAULT_FTP_SETTINGS.items()])
            quick(settings)
            ftp = self.mavftp.MAVFTP(self.conn, self.target_system, self.target_component, settings=settings)
            if ftp.pending_reset_seq is None:  # answered
                return ftp
            if time.monotonic() > deadline:
                raise UploadFailed(EXIT_TIMEOUT, f"the robot does not answer MAVLink FTP ({tries} ResetSessions "
                                                 f"unanswered in {wait_s:.0f} s; wrong or missing --signing-key?)")

    def request(self, ftp, opcode: int, command: str, args: list[str]) -> tuple[int, bytes] | None:
        """Run one single-reply MAVFTP command; the robot's (opcode, data) reply, or
        None if it was lost. Matched by the request's own seq, which MAVFTP takes
        from `ftp.seq` when it sends."""
        seq = ftp.seq
        ftp.cmd_ftp([command, *args])
        return self.ftp_replies.get((opcode, (seq + 1) % 65536))

    def remote_crc(self, ftp, path: str, wait_s: float = 20.0) -> int | None:
        """CalcFileCRC32 of `path`, None if the file does not exist.

        A request that seems lost is sent again, and a late reply to any of the
        earlier ones counts too (they all ask the same question)."""
        op_crc = self.mavftp.OP_CalcFileCRC32
        deadline = time.monotonic() + wait_s
        seqs = []
        while True:
            seqs.append(ftp.seq)
            ftp.cmd_ftp(["crc", path])
            for seq in seqs:
                reply = self.ftp_replies.get((op_crc, (seq + 1) % 65536))
                if reply is None:
                    continue
                opcode, data = reply
                if opcode == self.mavftp.OP_Ack and len(data) == 4:
                    return struct.unpack("<I", data)[0]
                return None
            if time.monotonic() > deadline:
                raise UploadFailed(EXIT_TIMEOUT, f"no CRC reply for {path} to {len(seqs)} requests in {wait_s:.0f} s")

    def read_param(self, name: str, tries: int = 3, timeout_s: float = 1.0):
        for _ in range(tries):
            self.params.pop(name, None)
            self.conn.mav.param_request_read_send(self.target_system, self.target_component,
                                                  name.encode(), -1)
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                self.conn.recv_match(blocking=True, timeout=0.1)
                if name in self.params:
                    return self.params[name]
        return None

    def close(self) -> None:
        self.conn.close()


# pymavlink MAVFTP's own defaults (mavftp.MAVFTP.__init__).
DEFAULT_FTP_SETTINGS = {"debug": 0, "pkt_loss_tx": 0, "pkt_loss_rx": 0, "max_backlog": 5,
                        "burst_read_size": 80, "write_size": 80, "write_qsize": 5,
                        "idle_detection_time": 3.7, "read_retry_time": 1.0, "retry_time": 0.5}


def quick(settings) -> None:
    """Single-reply operations (CRC, Rename, ResetSessions) have no completion
    signal in MAVFTP: it waits `idle_detection_time` of silence after the
    reply. A 57600 link answers in tens of ms, so wait 0.8 s instead of 3.7 s;
    a reply later than that counts as lost and the caller asks again."""
    settings.read_retry_time = 0.5
    settings.idle_detection_time = 0.8


def patient(settings) -> None:
    """pymavlink's defaults, for the put itself (its retry timers run up to 1 s)."""
    settings.idle_detection_time = DEFAULT_FTP_SETTINGS["idle_detection_time"]
    settings.read_retry_time = DEFAULT_FTP_SETTINGS["read_retry_time"]


def _float32(value: int) -> float:
    """What a PARAM_VALUE carries for an integer parameter (C cast to float32)."""
    return struct.unpack("<f", struct.pack("<f", float(value)))[0]


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
    except PolicyError:
        pass  # not a policy this build can load: the robot will judge it
    deadline = time.monotonic() + deadline_s
    t0 = time.monotonic()
    mavftp = link.mavftp
    ftp = None
    for attempt in range(1, attempts + 1):
        if time.monotonic() > deadline:
            raise UploadFailed(EXIT_TIMEOUT, f"upload not verified within {deadline_s:.0f} s")
        res.put_attempts = attempt
        ftp = link.ftp(wait_s=min(15.0, max(2.0, deadline - time.monotonic())))
        patient(ftp.ftp_settings)
        put_session = ftp.session  # the robot numbers the session as we do
        ftp.cmd_put([str(local), remote], progress_callback=progress)
        ftp.process_ftp_reply("put", timeout=max(10.0, deadline - time.monotonic()))
        quick(ftp.ftp_settings)
        crc = link.remote_crc(ftp, remote)
        if crc is None:
            # Not there: if only the TerminateSession was lost (pymavlink never
            # repeats it) the data waits under a temporary name until the
            # session expires; end that session again and look once more.
            ftp.session = put_session
            ftp.cmd_cancel()
            crc = link.remote_crc(ftp, remote)
        if crc == res.crc:
            break
        if crc is not None and attempt == attempts:
            raise UploadFailed(EXIT_MISMATCH, f"robot CRC32 0x{crc:08x} != local 0x{res.crc:08x} for {remote}")
    else:
        raise UploadFailed(EXIT_TIMEOUT, f"{remote} not on the robot after {attempts} puts")
    res.put_seconds = time.monotonic() - t0
    if not activate:
        return res

    # Rename onto active.qtab; every outcome is decided by the robot's reply or,
    # if that is lost, by what active.qtab now holds.
    for _ in range(attempts):
        if time.monotonic() > deadline:
            raise UploadFailed(EXIT_TIMEOUT, "activation not confirmed in time")
        n_texts = len(link.texts)
        reply = link.request(ftp, mavftp.OP_Rename, "rename", [remote, ACTIVE_POLICY])
        if reply is not None and reply[0] == mavftp.OP_Ack:
            res.activated = True
            break
        if reply is not None and reply[1][:1] == bytes([1]):  # NAK Fail: refused by the vehicle
            end = time.monotonic() + 1.0
            while time.monotonic() < end and not any("refused" in t for t in link.texts[n_texts:]):
                link.conn.recv_match(blocking=True, timeout=0.1)
            reasons = [t for t in link.texts[n_texts:] if "refused" in t]
            raise UploadFailed(EXIT_REFUSED, reasons[-1] if reasons else "robot refused the policy (reason lost)")
        if link.remote_crc(ftp, ACTIVE_POLICY) == res.crc:
            res.activated = True  # the rename happened; only its reply was lost
            break
        if reply is not None:
            code = reply[1][0] if reply[1] else 0
            raise UploadFailed(EXIT_REFUSED, f"robot rejected the rename (FTP NAK {code})")
    if not res.activated:
        raise UploadFailed(EXIT_TIMEOUT, "no answer to the activation rename")
    res.texts = list(link.texts)

    confirm_activation(link, ftp, res, deadline)
    return res


def confirm_activation(link: RobotLink, ftp, res: UploadResult, deadline: float) -> None:
    """The robot must report the new policy: its read-only parameters
    POLICY_CRC_HI/LO (exact) and POLICY_ID (float32 on the wire, so compared at
    float32 precision) against the file. A robot serving no parameters (the
    standalone FTP shell) is checked by the CRC of active.qtab instead."""
    first = link.read_param("POLICY_ID", tries=2)
    if first is not None and res.policy_id is not None and res.policy_crc is not None:
        want = {"POLICY_ID": _float32(res.policy_id), "POLICY_CRC_HI": float(res.policy_crc >> 16),
                "POLICY_CRC_LO": float(res.policy_crc & 0xFFFF)}
        give_up = min(deadline, time.monotonic() + 10.0)
        while True:  # the swap happens between two control ticks: allow it a moment
            got = {name: link.read_param(name) for name in want}
            values = {k: (m.param_value if m is not None else None) for k, m in got.items()}
            if values == want:
                res.confirmed_by = "POLICY_ID/POLICY_CRC params"
                return
            if time.monotonic() > give_up:
                raise UploadFailed(EXIT_MISMATCH, f"robot reports {values}, file has {want}")
            time.sleep(0.2)
    crc = link.remote_crc(ftp, ACTIVE_POLICY)
    if crc != res.crc:
        shown = "missing" if crc is None else f"0x{crc:08x}"
        raise UploadFailed(EXIT_MISMATCH, f"{ACTIVE_POLICY} CRC32 is {shown} after activation, expected 0x{res.crc:08x}")
    res.confirmed_by = "active.qtab CRC (robot serves no POLICY_ID parameter)"


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

    from firmware_py.signing import load_key_file

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
