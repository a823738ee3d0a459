"""The ground station's MAVLink link to the robot, shared by every command.

Owns: opening a pymavlink connection in MAVLink 2 (MAVLINK20=1 before pymavlink is imported, so a
signing setup survives), the signing key file, a `.tlog` of every session in both directions (by
default under `runs/tlogs/`; 8-byte big-endian µs timestamp + raw frame, what `mavlogdump.py`
reads), finding the robot by its HEARTBEAT, and the request/answer patterns with timeouts and
retries: COMMAND_LONG -> COMMAND_ACK, PARAM_* -> PARAM_VALUE, the mission upload/download exchange.

It also overhears what every command may need later: STATUSTEXTs
(reassembled from their MAVLink 2 chunks by `statustext.StatusTextAssembler`,
so `texts` holds whole texts only, as MAVProxy shows them), the newest PARAM_VALUE of each name (`read_params` asks for several at once and
waits for wanted values), the robot's HEARTBEAT system state. FTP upload
(`ground_station.mavlink.ftp_upload`) runs on the same connection.

Refusals, timeouts and mismatches raise `LinkError(code, one line)`; the line carries the robot's
reason (the STATUSTEXT it sent with the refusal). `code` is the exit status of every MAVLink
command: EXIT_REFUSED 3, EXIT_TIMEOUT 4 (timeout, no robot, no answer), EXIT_MISMATCH 5 (what the
robot reports is not what was sent). 2 (bad arguments) is `CliError`'s.

One-shot commands send no HEARTBEAT: the robot's GCS failsafe watches
ground-station heartbeats, and a command that exits would trip it 5 s later.
A long-running tool (`qnav monitor`, MAVProxy) passes `heartbeat=True`.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import struct
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from firmware_py.mavlink.dialect import NAME as DIALECT
from firmware_py.mavlink.params import as_float32
from ground_station.mavlink.statustext import StatusTextAssembler

EXIT_REFUSED, EXIT_TIMEOUT, EXIT_MISMATCH = 3, 4, 5
DEFAULT_URL = "udpin:127.0.0.1:14550"
DEFAULT_TLOG_DIR = Path("runs") / "tlogs"
DEFAULT_TIMEOUT_S = 10.0  # heartbeat wait
# Our own MAVLink identity: system 255, the robot's SYSID_MYGCS default; component 25
# (MAV_COMP_ID_USER1), so replies to QGroundControl (190) or MAVProxy (230) on the same link stay apart.
GCS_SYSID, GCS_COMPID = 255, 25
MAV_TYPE_GCS = 6
MAV_STATE_UNINIT = 0
PARAM_ASK_INTERVAL_S = 0.5  # read_params: re-ask an unanswered PARAM_REQUEST_READ after this long


class LinkError(Exception):
    """A refusal, timeout or mismatch, with the exit code the command should return."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code


def mavutil():
    """pymavlink's mavutil, imported in MAVLink 2 mode."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil as mu

    return mu


def mavlink():
    return mavutil().mavlink


ENV_URL = "QNAV_MAVLINK"  # the environment's default for --mavlink (add_link_args)
SITL_GCS_URL = "udpout:127.0.0.1:14555"  # how a GCS reaches `qnav sitl`'s robot by default (ground_station/sitl.py)
URL_SCHEMES = ("udpin", "udpout", "udp", "udpbcast", "tcp", "tcpin", "mcast")
WAIT_NOTICE_S = 1.0  # say what we wait for once a wait has lasted this long


def check_url(url: str) -> str | None:
    """None if `url` is a connection string pymavlink can open, else the one-line reason.

    Accepted: SCHEME:HOST:PORT for the UDP/TCP schemes, a serial device
    (a path that exists, `/dev/...`, `COMn`), optionally `DEVICE,BAUD`."""
    head, sep, rest = url.partition(":")
    if sep and head in URL_SCHEMES:
        host, sep2, port = rest.rpartition(":")
        if head == "mcast" and not rest:
            return None
        if not sep2 or not host:
            return f"{url!r}: expected {head}:HOST:PORT"
        if not port.isdigit() or not 0 < int(port) < 65536:
            return f"{url!r}: port must be a number 1-65535, got {port!r}"
        return None
    device = url.split(",", 1)[0]
    if device.startswith("/dev/") or os.path.exists(device) or (device.upper().startswith("COM")
                                                                 and device[3:].isdigit()):
        baud = url.split(",", 1)[1] if "," in url else "1"
        return None if baud.isdigit() else f"{url!r}: baud rate must be a number, got {baud!r}"
    return (f"{url!r} is not a MAVLink connection string: use "
            f"{'|'.join(s for s in URL_SCHEMES if s != 'mcast')}:HOST:PORT or a serial device")


def default_url() -> str:
    """The link a command uses without --mavlink: $QNAV_MAVLINK when set, else DEFAULT_URL."""
    return os.environ.get(ENV_URL) or DEFAULT_URL


def where_url_came_from(url: str) -> str:
    """For a "waiting for a robot on URL" line: where `url` came from and how to give another."""
    if url == os.environ.get(ENV_URL):
        return f"from ${ENV_URL}; --mavlink URL overrides it"
    if url == DEFAULT_URL:
        return (f"the default URL: give --mavlink URL or export {ENV_URL}=URL, e.g. {SITL_GCS_URL} for "
                "`qnav sitl`'s robot, which prints its URL")
    return f"from --mavlink; export {ENV_URL}=URL sets it once per shell"


def _url_arg(value: str) -> str:
    problem = check_url(value)
    if problem is not None:
        if value == os.environ.get(ENV_URL) and value != DEFAULT_URL:
            problem = f"{problem} (from ${ENV_URL})"
        raise argparse.ArgumentTypeError(problem)
    return value


def _checked(text: str, convert, expected: str, ok, problem: str):  # type: ignore[no-untyped-def]
    """An argparse value `convert(text)`, refused in one line as not `expected` or when not `ok`
    (`problem` formatted with the text as given)."""
    try:
        x = convert(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
    if not ok(x):
        raise argparse.ArgumentTypeError(problem.format(text))
    return x


def _positive_seconds(value: str) -> float:
    return float(_checked(value, float, "seconds", lambda x: 0 < x < float("inf"), "must be > 0 seconds, got {}"))


def finite_float(value: str) -> float:
    """argparse type for a coordinate: a finite number (float() also takes
    "nan" and "inf", which nothing downstream can place)."""
    return float(_checked(value, float, "a number", math.isfinite, "must be a finite number, got {}"))


def _sysid(value: str) -> int:
    return int(_checked(value, int, "a system id 1-254", lambda x: 1 <= x <= 254, "system id must be 1-254, got {}"))


def _id_arg(what: str, lo: int):  # type: ignore[no-untyped-def]
    def parse(value: str) -> int:
        return int(_checked(value, int, f"a {what} id {lo}-255", lambda x: lo <= x <= 255,
                            f"{what} id must be {lo}-255, got {{}}"))
    return parse


def add_link_args(parser: argparse.ArgumentParser, *, timeout_s: float = DEFAULT_TIMEOUT_S,
                  timeout_help: str | None = None, url_default: str | None = DEFAULT_URL) -> None:
    """The link options of every MAVLink command. `--timeout` is the heartbeat wait unless the
    command gives it a wider meaning (`timeout_s`, `timeout_help`: `qnav upload`'s whole budget).
    The URL, or `QNAV_MAVLINK` replacing the default, is checked when parsed (exit 2)."""
    if url_default == DEFAULT_URL:
        url_default = default_url()
    parser.add_argument("--mavlink", metavar="URL", default=url_default, type=_url_arg,
                        help=f"pymavlink connection string (default {DEFAULT_URL}, or ${ENV_URL} when set; "
                             "udpout:, tcp:, serial also)")
    parser.add_argument("--signing-key", metavar="FILE", default=None,
                        help="MAVLink 2 signing key file (32 bytes, 64 hex chars or a passphrase)")
    tl = parser.add_mutually_exclusive_group()
    tl.add_argument("--tlog", metavar="FILE", default=None,
                    help=f"session log (default: a new file under {DEFAULT_TLOG_DIR}/)")
    tl.add_argument("--no-tlog", action="store_true", help="do not write a session log")
    parser.add_argument("--timeout", type=_positive_seconds, default=timeout_s, metavar="S",
                        help=timeout_help or f"seconds to wait for the robot's heartbeat (> 0, default {timeout_s:g})")
    parser.add_argument("--target-system", type=_sysid, default=None, metavar="SYSID",
                        help="talk to this system id only (default: the first robot heard); "
                             "frames from other systems are ignored and counted")
    parser.add_argument("--source-system", type=_id_arg("system", 1), default=GCS_SYSID, metavar="SYSID",
                        help=f"our own system id (default {GCS_SYSID}: the robot's SYSID_MYGCS default, so our "
                             "heartbeats keep its GCS failsafe alive)")
    parser.add_argument("--source-component", type=_id_arg("component", 1), default=GCS_COMPID, metavar="COMPID",
                        help=f"our own component id (default {GCS_COMPID}, MAV_COMP_ID_USER1: not QGroundControl's "
                             "190 nor MAVProxy's 230; give two qnav stations on one robot different ones)")


@dataclass
class CommandResult:
    result: int
    texts: list[str]


RECEIVE_BUFFER_BYTES = 4 * 1024 * 1024


def _widen_receive_buffer(conn: Any) -> None:
    """A UDP link's kernel receive buffer to 4 MiB: a robot on a fast sim clock streams its telemetry
    faster, and a burst overflowing Linux's default loses once-sent STATUSTEXTs. Best effort:
    SO_RCVBUFFORCE where allowed, else SO_RCVBUF (capped at net.core.rmem_max); serial has none."""
    import socket

    port = getattr(conn, "port", None)
    if isinstance(port, socket.socket) and port.type == socket.SOCK_DGRAM:
        for option in (getattr(socket, "SO_RCVBUFFORCE", None), socket.SO_RCVBUF):
            if option is None:
                continue
            with contextlib.suppress(OSError):
                port.setsockopt(socket.SOL_SOCKET, option, RECEIVE_BUFFER_BYTES)
                return


class Link:
    """A connection to one robot. Use as a context manager."""

    def __init__(self, url: str = DEFAULT_URL, *, signing_key: str | os.PathLike[str] | None = None,
                 tlog: str | os.PathLike[str] | Literal[False] | None = None, name: str = "session",
                 heartbeat: bool = False, source_system: int = GCS_SYSID,
                 source_component: int = GCS_COMPID, target_system: int | None = None) -> None:
        mu = mavutil()
        self.m = mu.mavlink
        self.conn = mu.mavlink_connection(url, source_system=source_system, source_component=source_component,
                                          dialect=DIALECT, autoreconnect=True)
        _widen_receive_buffer(self.conn)
        self.source_system = source_system  # frames from this system id are ours (or another GCS's)
        self.url = url
        self.key: bytes | None = None
        if signing_key is not None:
            from firmware_py.mavlink.signing import load_key_file

            self.key = load_key_file(signing_key)
            self.conn.setup_signing(self.key, sign_outgoing=True, allow_unsigned_callback=None)
        self.tlog_path: Path | None = None
        self._tlog = None
        self._tlog_lock = threading.Lock()
        if tlog is not False:
            self.tlog_path = Path(tlog) if tlog else default_tlog_path(name)
            self.tlog_path.parent.mkdir(parents=True, exist_ok=True)
            self._tlog = open(self.tlog_path, "wb")  # noqa: SIM115 - closed in close()
            self.conn.message_hooks.append(lambda _conn, msg: self._write_tlog(msg))  # received
            self.conn.mav.set_send_callback(lambda msg, *_a, **_k: self._write_tlog(msg))  # sent
        self.texts: list[str] = []  # whole STATUSTEXTs from the robot, in arrival order
        self._assembler = StatusTextAssembler()
        self.want_sysid = target_system  # --target-system: None = the first robot heard
        self.foreign_frames: dict[int, int] = {}  # sysid -> frames ignored from a system not our robot
        self.bad_signatures = 0  # frames dropped because their signature did not verify with our key
        self.params: dict[str, tuple[float, float]] = {}  # name -> (value, monotonic time received)
        self.param_values_seen = 0
        self.system_status: int | None = None  # the robot's HEARTBEAT system_status
        self.conn.message_hooks.append(self._collect)
        self.target: tuple[int, int] | None = None
        # mission_upload: None sends items in the frame given; (lat_e7, lon_e7), the robot's origin
        # (`origin()`), sends LOCAL_NED items in MAV_FRAME_GLOBAL_RELATIVE_ALT around it (use_global_frame)
        self.mission_origin: tuple[int, int] | None = None
        # ground_station.mavlink.ftp_upload.FtpSession, made on the first FTP
        # request: one MAVFTP client per link, so its request seq never restarts
        self.ftp_session: Any = None
        self._hb_stop = threading.Event()
        self._hb_thread: threading.Thread | None = None
        self._heartbeat = heartbeat

    # --- session ---------------------------------------------------------------------
    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def stop_heartbeat(self) -> None:
        self._hb_stop.set()
        if self._hb_thread is not None:
            self._hb_thread.join(timeout=2)

    def close(self) -> None:
        self.stop_heartbeat()
        self.conn.close()
        with self._tlog_lock:
            if self._tlog is not None:
                self._tlog.close()
                self._tlog = None

    def _write_tlog(self, msg) -> None:
        with self._tlog_lock:
            if self._tlog is not None and msg.get_type() != "BAD_DATA":
                usec = int(time.time() * 1e6) & ~3
                self._tlog.write(struct.pack(">Q", usec) + bytes(msg.get_msgbuf()))
                self._tlog.flush()

    def _collect(self, _conn, msg) -> None:
        t = msg.get_type()
        if t == "BAD_DATA":
            if "signature" in str(getattr(msg, "reason", "")).lower():
                self.bad_signatures += 1
            return
        src = msg.get_srcSystem()
        if src != self.source_system and self.target is not None and src != self.target[0]:
            self.foreign_frames[src] = self.foreign_frames.get(src, 0) + 1
            return
        now = time.monotonic()
        done = self._assembler.add(msg, now) if t == "STATUSTEXT" else self._assembler.flush(now)
        for st in done:
            if st.sysid != self.source_system:
                self.texts.append(st.text)
        if t == "STATUSTEXT":
            return
        if t == "PARAM_VALUE":
            self.params[msg.param_id] = (msg.param_value, time.monotonic())
            self.param_values_seen += 1
        elif t == "HEARTBEAT" and src != self.source_system:
            self.system_status = msg.system_status

    def connect(self, timeout_s: float = DEFAULT_TIMEOUT_S,
                on_wait: Callable[[str], None] | None = None, url_note: str = "") -> tuple[int, int]:
        """Wait for the robot's HEARTBEAT (of `target_system` if given); returns
        (sysid, compid). `on_wait(line)` is told what we wait for once the wait
        has lasted WAIT_NOTICE_S (with `url_note`: where the URL came from, how to change it)."""
        start = time.monotonic()
        deadline = start + timeout_s
        next_poke = 0.0
        told = on_wait is None
        who = f"robot {self.want_sysid}" if self.want_sysid is not None else "a robot"
        while time.monotonic() < deadline:
            if not told and time.monotonic() - start >= WAIT_NOTICE_S:
                assert on_wait is not None
                on_wait(f"waiting for a HEARTBEAT from {who} on {self.url} (up to {timeout_s:g} s"
                        f"{'; ' + url_note if url_note else ''}) ...")
                told = True
            if time.monotonic() >= next_poke:
                # ask for a heartbeat now rather than waiting up to 1 s for the next one
                # (over udpin this goes out once the robot's first frame taught us its address)
                self.conn.mav.command_long_send(0, 0, self.m.MAV_CMD_REQUEST_MESSAGE, 0,
                                                self.m.MAVLINK_MSG_ID_HEARTBEAT, 0, 0, 0, 0, 0, 0)
                next_poke = time.monotonic() + 1.0
            msg = self.conn.recv_match(blocking=True, timeout=0.1)
            if msg is None or msg.get_type() == "BAD_DATA":
                continue
            if msg.get_type() != "HEARTBEAT":
                if msg.get_srcSystem() != self.source_system and next_poke - time.monotonic() > 0.2:
                    next_poke = time.monotonic() + 0.2  # the robot is there: poke again soon
                continue
            if msg.type != MAV_TYPE_GCS:
                if self.want_sysid is not None and msg.get_srcSystem() != self.want_sysid:
                    src = msg.get_srcSystem()
                    self.foreign_frames[src] = self.foreign_frames.get(src, 0) + 1
                    continue
                self.target = (msg.get_srcSystem(), msg.get_srcComponent())
                self.conn.target_system, self.conn.target_component = self.target
                if self._heartbeat:
                    self.start_heartbeat()
                return self.target
        raise LinkError(EXIT_TIMEOUT, f"no HEARTBEAT from {who} on {self.url} within {timeout_s:g} s"
                                      f"{self._no_heartbeat_hint()}")

    def _no_heartbeat_hint(self) -> str:
        if self.bad_signatures:
            return (f" ({self.bad_signatures} frames arrived whose signature does not verify with "
                    f"--signing-key: is it the robot's key?)")
        if self.foreign_frames:
            seen = ", ".join(str(s) for s in sorted(self.foreign_frames))
            return f" (heard only system(s) {seen}; check --target-system)"
        if self.key is not None:
            return " (signed; is it the robot's key?)"
        return ""

    def no_answer(self, what: str) -> LinkError:
        """The timeout error of a request the robot left unanswered, with a hint
        at signing when its heartbeats arrive but our requests are ignored."""
        return LinkError(EXIT_TIMEOUT, f"{what}{self._signing_hint()}")

    def start_heartbeat(self, period_s: float = 1.0) -> None:
        """Our GCS HEARTBEAT now and every `period_s` wall seconds from a thread of its own, until
        `stop_heartbeat` or `close` (a send that fails is tried again on the next beat)."""
        def beat() -> None:
            while not self._hb_stop.wait(period_s):
                with contextlib.suppress(OSError):
                    self.send_heartbeat()
        with contextlib.suppress(OSError):
            self.send_heartbeat()
        self._hb_thread = threading.Thread(target=beat, name="gcs-heartbeat", daemon=True)
        self._hb_thread.start()

    def send_heartbeat(self) -> None:
        self.conn.mav.heartbeat_send(MAV_TYPE_GCS, self.m.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    @property
    def sysid(self) -> int:
        assert self.target is not None, "connect() first"
        return self.target[0]

    @property
    def compid(self) -> int:
        assert self.target is not None, "connect() first"
        return self.target[1]

    def recv(self, types: str | list[str] | None = None, timeout_s: float = 1.0,
             cond: Callable[..., bool] | None = None):  # cond(msg); `...`: lambdas bind loop vars as defaults
        """Next message from the robot (of `types`, passing `cond`) or None."""
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            msg = self.conn.recv_match(type=types, blocking=True, timeout=left)
            if msg is None:
                return None
            if self.target is not None and msg.get_srcSystem() != self.target[0]:
                continue  # counted in foreign_frames by _collect
            if cond is None or cond(msg):
                return msg

    def _reason(self, since: int, fallback: str) -> str:
        """The robot's whole texts since index `since` (and any still arriving), one line."""
        new = [t for t in self.texts[since:] + self._assembler.pending() if t]
        return "; ".join(new) if new else fallback

    def wait_text(self, since: int, pred: Callable[[str], bool], timeout_s: float) -> str | None:
        """The first whole STATUSTEXT after index `since` passing `pred`, waiting up to `timeout_s`."""
        end = time.monotonic() + timeout_s
        while True:
            for t in self.texts[since:]:
                if pred(t):
                    return t
            if time.monotonic() >= end:
                return None
            self.conn.recv_match(blocking=True, timeout=min(0.05, max(0.0, end - time.monotonic())))

    # --- commands ----------------------------------------------------------------------
    def command(self, command: int, *params: float, timeout_s: float = 1.5, retries: int = 3,
                check: bool = True) -> CommandResult:
        """COMMAND_LONG with retries until its COMMAND_ACK; raises on refusal if `check`."""
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        name = _enum_name(self.m, "MAV_CMD", command)
        since = len(self.texts)
        for attempt in range(retries + 1):
            self.conn.mav.command_long_send(self.sysid, self.compid, command, attempt, *p)
            ack = self.recv("COMMAND_ACK", timeout_s, cond=lambda a: a.command == command)
            if ack is None:
                continue
            self.recv("STATUSTEXT", 0.05)  # a reason sent just before the ACK may still be queued
            texts = self.texts[since:]
            if check and ack.result != self.m.MAV_RESULT_ACCEPTED:
                result = _enum_name(self.m, "MAV_RESULT", ack.result)
                raise LinkError(EXIT_REFUSED, f"{name}: {result}: {self._reason(since, 'no reason given')}")
            return CommandResult(ack.result, texts)
        raise self.no_answer(f"{name}: no COMMAND_ACK after {retries + 1} tries")

    def set_goal(self, x_m: float, y_m: float, timeout_s: float = 1.5, retries: int = 3) -> None:
        """Guided goal at world (x east, y north) metres, re-sent until the robot echoes it in
        POSITION_TARGET_LOCAL_NED; raises with its "goal refused: ..." STATUSTEXT or on silence."""
        since = len(self.texts)
        mask = 0xFFF8  # position only
        for _ in range(retries):
            self.conn.mav.set_position_target_local_ned_send(0, self.sysid, self.compid, self.m.MAV_FRAME_LOCAL_NED,
                                                             mask, y_m, x_m, 0, 0, 0, 0, 0, 0, 0, 0, 0)
            end = time.monotonic() + timeout_s
            while time.monotonic() < end:
                reply = self.recv("POSITION_TARGET_LOCAL_NED", min(0.1, end - time.monotonic()))
                reason = self.wait_text(since, lambda t: t.startswith("goal refused"), 0.0)
                if reason is not None:
                    raise LinkError(EXIT_REFUSED, reason)
                if reply is not None and abs(reply.x - y_m) < 0.01 and abs(reply.y - x_m) < 0.01:
                    return
        raise self.no_answer("goal: no echo from the robot")

    def _signing_hint(self) -> str:
        hb = self.conn.messages.get("HEARTBEAT")
        buf = bytes(hb.get_msgbuf()) if hb is not None else b""
        if self.key is None and len(buf) > 2 and buf[0] == 0xFD and buf[2] & 0x01:
            return " (the robot signs its frames: it ignores unsigned commands; use --signing-key FILE)"
        if self.key is not None and self.target is not None:
            return (" (its heartbeats arrive but it answers nothing: does it use this --signing-key, "
                    "or no signing at all?)")
        return ""

    # --- parameters ----------------------------------------------------------------------
    def param_list(self, timeout_s: float = 3.0, retries: int = 3) -> dict[str, float]:
        """All parameters in index order; missing indices are re-read one by one."""
        values: dict[int, tuple[str, float]] = {}
        count = None
        self.conn.mav.param_request_list_send(self.sysid, self.compid)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and (count is None or len(values) < count):
            pv = self.recv("PARAM_VALUE", min(0.5, max(0.01, deadline - time.monotonic())))
            if pv is None:
                if count is not None:
                    break
                continue
            count = pv.param_count
            values[pv.param_index] = (pv.param_id, pv.param_value)
        if count is None:
            raise self.no_answer("no PARAM_VALUE answer to PARAM_REQUEST_LIST")
        for index in range(count):
            for _ in range(retries):
                if index in values:
                    break
                self.conn.mav.param_request_read_send(self.sysid, self.compid, b"", index)
                pv = self.recv("PARAM_VALUE", 1.0, cond=lambda p, i=index: p.param_index == i)
                if pv is not None:
                    values[index] = (pv.param_id, pv.param_value)
            if index not in values:
                raise LinkError(EXIT_TIMEOUT, f"parameter #{index} never arrived")
        return dict(values[i] for i in range(count))

    def param_get(self, name: str, timeout_s: float = 1.0, retries: int = 3) -> float:
        since = len(self.texts)
        for _ in range(retries):
            self.conn.mav.param_request_read_send(self.sysid, self.compid, name.encode(), -1)
            end = time.monotonic() + timeout_s
            while time.monotonic() < end:
                pv = self.recv(["PARAM_VALUE", "STATUSTEXT"], end - time.monotonic(),
                               cond=lambda p: p.get_type() == "STATUSTEXT" or p.param_id == name)
                if pv is None:
                    break
                if pv.get_type() == "PARAM_VALUE":
                    return pv.param_value
                refusal = self.wait_text(since, lambda t: name in t, 0.0)  # "unknown parameter NAME"
                if refusal is not None:
                    raise LinkError(EXIT_REFUSED, refusal)
        if self.texts[since:]:
            raise LinkError(EXIT_TIMEOUT, self._reason(since, ""))
        raise self.no_answer(f"no PARAM_VALUE for {name}")

    def param_set(self, name: str, value: float, timeout_s: float = 1.0, retries: int = 3) -> float:
        """Set and verify the echo; raises with the robot's reason if it kept another value."""
        since = len(self.texts)
        want = as_float32(round(value))  # an INT32 parameter: the robot keeps the integer and echoes it
        for _ in range(retries):
            self.conn.mav.param_set_send(self.sysid, self.compid, name.encode(), float(value),
                                         self.m.MAV_PARAM_TYPE_INT32)
            # a refusal comes as a (possibly chunked) STATUSTEXT naming the
            # parameter, then the PARAM_VALUE with the kept value
            pv = self.recv("PARAM_VALUE", timeout_s, cond=lambda p: p.param_id == name)
            if pv is None:
                refusal = self.wait_text(since, lambda t: name in t, 0.0)
                if refusal is not None:
                    raise LinkError(EXIT_REFUSED, refusal)
                continue
            if pv.param_value != want:
                refusal = self.wait_text(since, lambda t: name in t, 0.2)
                raise LinkError(EXIT_REFUSED, refusal or self._reason(since, f"{name} stayed {pv.param_value:g}"))
            return pv.param_value
        raise self.no_answer(f"no PARAM_VALUE echo for {name}")

    def read_params(self, names: Iterable[str], budget_s: float = 10.0,
                    want: dict[str, float] | None = None) -> dict[str, float | None]:
        """Values of `names` the robot sent after this call began (None: not answered within
        `budget_s`). A name is asked again every PARAM_ASK_INTERVAL_S until answered and, with
        `want`, until it equals its wanted value (the POLICY_* mirror follows on the next tick)."""
        names = list(names)
        t0 = time.monotonic()
        end = t0 + budget_s
        asked: dict[str, float] = {}

        def fresh(name: str) -> float | None:
            got = self.params.get(name)
            return got[0] if got is not None and got[1] >= t0 else None

        def done(name: str) -> bool:
            value = fresh(name)
            return value is not None and (want is None or value == want[name])

        while True:
            now = time.monotonic()
            for name in names:
                if not done(name) and now - asked.get(name, -1e9) >= PARAM_ASK_INTERVAL_S:
                    self.conn.mav.param_request_read_send(self.sysid, self.compid, name.encode(), -1)
                    asked[name] = now
            if all(done(n) for n in names) or now > end:
                return {n: fresh(n) for n in names}
            self.conn.recv_match(blocking=True, timeout=0.05)  # the hook records what arrives

    @property
    def serves_params(self) -> bool:
        """The robot's node reports a system state in its HEARTBEAT and serves parameters (POLICY_*
        among them); the bare FTP shell reports MAV_STATE_UNINIT and serves none."""
        return self.param_values_seen > 0 or self.system_status not in (None, MAV_STATE_UNINIT)

    # --- missions --------------------------------------------------------------------------
    def origin(self, timeout_s: float = 1.0, retries: int = 3) -> tuple[int, int, int]:
        """The robot's geodetic origin (lat, lon in 1e-7 deg, altitude AMSL in mm) from its
        GPS_GLOBAL_ORIGIN, asked for with MAV_CMD_REQUEST_MESSAGE: exact, unlike its
        ORIGIN_* parameters, whose PARAM_VALUEs carry a float32 (steps of up to 18 cm)."""
        m = self.m
        for _ in range(retries + 1):
            self.conn.mav.command_long_send(self.sysid, self.compid, m.MAV_CMD_REQUEST_MESSAGE, 0,
                                            m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, 0, 0, 0, 0, 0, 0)
            msg = self.recv("GPS_GLOBAL_ORIGIN", timeout_s)
            if msg is not None:
                return int(msg.latitude), int(msg.longitude), int(msg.altitude)
        raise self.no_answer(f"no GPS_GLOBAL_ORIGIN from the robot after {retries + 1} requests "
                             "(its geodetic origin, which global mission items are placed around)")

    def use_global_frame(self) -> tuple[int, int, int]:
        """From now on `mission_upload` sends LOCAL_NED items in MAV_FRAME_GLOBAL_RELATIVE_ALT around
        the robot's origin (as ArduPilot and QGroundControl do), so every ground station's map shows
        them where they are. Returns the origin."""
        origin = self.origin()
        self.mission_origin = origin[0], origin[1]
        return origin

    def mission_upload(self, items: list[tuple[int, int, int]], timeout_s: float = 2.0, retries: int = 3) -> int:
        """Upload NAV_WAYPOINT items (frame, x, y as MISSION_ITEM_INT); returns the count.
        With `mission_origin` set, LOCAL_NED items go in MAV_FRAME_GLOBAL_RELATIVE_ALT."""
        m = self.m
        if self.mission_origin is not None:
            from firmware_py.mavlink.frames import local_item_to_global

            lat0, lon0 = self.mission_origin
            items = [(m.MAV_FRAME_GLOBAL_RELATIVE_ALT, *local_item_to_global(x, y, lat0, lon0))
                     if frame == m.MAV_FRAME_LOCAL_NED else (frame, x, y) for frame, x, y in items]
        since = len(self.texts)
        sent_count = 0
        for _ in range(retries + 1):
            self.conn.mav.mission_count_send(self.sysid, self.compid, len(items), m.MAV_MISSION_TYPE_MISSION)
            sent_count += 1
            while True:
                msg = self.recv(["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"], timeout_s)
                if msg is None:
                    break  # silence: start over (the robot cancels a stalled upload itself)
                if msg.get_type() == "MISSION_ACK":
                    if msg.type == m.MAV_MISSION_ACCEPTED:
                        return len(items)
                    result = _enum_name(m, "MAV_MISSION_RESULT", msg.type)
                    raise LinkError(EXIT_REFUSED, f"mission upload: {result}: {self._reason(since, 'no reason given')}")
                seq = msg.seq
                if not 0 <= seq < len(items):
                    continue
                frame, x, y = items[seq]
                self.conn.mav.mission_item_int_send(self.sysid, self.compid, seq, frame, m.MAV_CMD_NAV_WAYPOINT,
                                                    0, 1, 0, 0, 0, 0, x, y, 0, m.MAV_MISSION_TYPE_MISSION)
        raise self.no_answer(f"mission upload: no MISSION_ACK after {sent_count} MISSION_COUNT")

    def mission_download(self, timeout_s: float = 1.5, retries: int = 3) -> list:
        """All mission items (MISSION_ITEM_INT messages) in order."""
        m = self.m
        count = None
        for _ in range(retries + 1):
            self.conn.mav.mission_request_list_send(self.sysid, self.compid, m.MAV_MISSION_TYPE_MISSION)
            msg = self.recv("MISSION_COUNT", timeout_s)
            if msg is not None:
                count = msg.count
                break
        if count is None:
            raise self.no_answer("mission download: no MISSION_COUNT")
        items = []
        for seq in range(count):
            for _ in range(retries + 1):
                self.conn.mav.mission_request_int_send(self.sysid, self.compid, seq, m.MAV_MISSION_TYPE_MISSION)
                it = self.recv(["MISSION_ITEM_INT", "MISSION_ACK"], timeout_s,
                               cond=lambda x, s=seq: x.get_type() == "MISSION_ACK" or x.seq == s)
                if it is not None and it.get_type() == "MISSION_ACK":
                    raise LinkError(EXIT_REFUSED, f"mission download: item {seq} refused "
                                                  f"({_enum_name(m, 'MAV_MISSION_RESULT', it.type)})")
                if it is not None:
                    items.append(it)
                    break
            else:
                raise LinkError(EXIT_TIMEOUT, f"mission download: item {seq} never arrived")
        self.conn.mav.mission_ack_send(self.sysid, self.compid, m.MAV_MISSION_ACCEPTED, m.MAV_MISSION_TYPE_MISSION)
        return items


def _enum_name(m, enum: str, value: int) -> str:
    entry = m.enums.get(enum, {}).get(value)
    if entry is None:
        return str(value)
    return entry.name.removeprefix(f"{enum}_").removeprefix("MAV_RESULT_").removeprefix("MAV_MISSION_")


def default_tlog_path(name: str) -> Path:
    stamp = time.strftime("%Y%m%d-%H%M%S")
    return DEFAULT_TLOG_DIR / f"{stamp}-{name.replace(' ', '-')}-{os.getpid()}.tlog"  # no spaces in file names


def open_link(args: argparse.Namespace, name: str, heartbeat: bool = False,
              connect_timeout_s: float | None = None) -> Link:
    """Open and connect a `Link` from the common command-line options (the
    heartbeat wait is `--timeout` unless `connect_timeout_s` is given)."""
    tlog: str | Literal[False] | None = False if getattr(args, "no_tlog", False) else getattr(args, "tlog", None)
    url = args.mavlink or DEFAULT_URL
    from ground_station.errors import CliError

    problem = check_url(url)
    if problem is not None:
        raise CliError(f"--mavlink {problem}")
    try:
        link = Link(url, signing_key=args.signing_key, tlog=tlog, name=name, heartbeat=heartbeat,
                    target_system=getattr(args, "target_system", None),
                    source_system=getattr(args, "source_system", GCS_SYSID),
                    source_component=getattr(args, "source_component", GCS_COMPID))
    except ValueError as exc:  # bad key file
        raise CliError(str(exc)) from exc
    except OSError as exc:
        raise CliError(f"cannot open {url}: {exc}") from exc
    try:
        link.connect(connect_timeout_s if connect_timeout_s is not None
                     else getattr(args, "timeout", DEFAULT_TIMEOUT_S),
                     on_wait=lambda line: print(f"qnav {name}: {line}", file=sys.stderr, flush=True),
                     url_note=where_url_came_from(url))
    except BaseException:
        link.close()
        raise
    return link


def run_on_link(args: argparse.Namespace, name: str, body: Callable[[Link], int]) -> int:
    """Open the link, run `body`, print a LinkError as one line with its exit code."""
    try:
        with open_link(args, name) as link:
            code = body(link)
            warn_foreign(link, name)
            return code
    except LinkError as exc:
        text = str(exc)
        text = text[len(name) + 2:] if text.startswith(f"{name}: ") else text  # not "mission upload: mission upload:"
        print(f"qnav {name}: {text}", file=sys.stderr)
        return exc.code


def warn_foreign(link: Link, name: str) -> None:
    """One stderr line when frames from systems other than our robot were ignored."""
    if link.foreign_frames:
        counts = ", ".join(f"system {s}: {n}" for s, n in sorted(link.foreign_frames.items()))
        print(f"qnav {name}: warning: ignored frames from other systems ({counts}); "
              f"talking to system {link.target[0] if link.target else '?'}", file=sys.stderr)
