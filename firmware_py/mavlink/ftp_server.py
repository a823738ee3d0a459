"""MAVLink FTP server (FILE_TRANSFER_PROTOCOL, msg 110) as a pure state machine.

`FtpServer.handle(payload, now_us) -> list[bytes]` takes the 251-byte FTP payload of one request and
returns the FTP payloads to send back (none, one, or a burst). No sockets, no threads, no wall
clock: the shell (`ground_station.lab.rigs.ftp_shell` or the MAVLink node) wraps replies in
FILE_TRANSFER_PROTOCOL addressed to the requester and drains `drain_texts()` into STATUSTEXT.

The protocol rules it follows (sessions, the retry cache, commits, activation by Rename, malformed
input): docs/mavlink.md, "FTP server" and "Policy activation". Costly file work runs on the
injected `offload`, its reply coming from `poll`.
"""

from __future__ import annotations

import errno
import functools
import os
import struct
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

from firmware_py.background import Background
from firmware_py.mavlink.metadata import GENERAL_FILE, METADATA_DIR, PARAMETER_FILE
from firmware_py.mavlink.signing import SIGNING_FILE
from firmware_py.onboard_log import LOG_DIR
from firmware_py.storage import (
    ACTIVE_MAP,
    ACTIVE_POLICY,
    LAST_GOOD_MAP,
    LAST_GOOD_POLICY,
    LAYOUT_DIRS,
    PARAMS_FILE,
    UID_FILE,
    Storage,
    Upload,
    commit_promotion,
    policy_source,
    promote_policy,
)
from firmware_py.vehicle import ACTIVATION_TIMEOUT_S

HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst_complete, pad, offset
MAX_DATA = 239
PAYLOAD_LEN = HEADER.size + MAX_DATA  # 251

SEVERITY_WARNING = 4
SEVERITY_INFO = 6


class Op(IntEnum):
    NONE = 0
    TERMINATE_SESSION = 1
    RESET_SESSIONS = 2
    LIST_DIRECTORY = 3
    OPEN_FILE_RO = 4
    READ_FILE = 5
    CREATE_FILE = 6
    WRITE_FILE = 7
    REMOVE_FILE = 8
    CREATE_DIRECTORY = 9
    REMOVE_DIRECTORY = 10
    OPEN_FILE_WO = 11
    TRUNCATE_FILE = 12
    RENAME = 13
    CALC_FILE_CRC32 = 14
    BURST_READ_FILE = 15
    LIST_DIRECTORY_WITH_TIME = 16
    ACK = 128
    NAK = 129


class Nak(IntEnum):
    FAIL = 1
    FAIL_ERRNO = 2
    INVALID_DATA_SIZE = 3
    INVALID_SESSION = 4
    NO_SESSIONS_AVAILABLE = 5
    EOF = 6
    UNKNOWN_COMMAND = 7
    FILE_EXISTS = 8
    FILE_PROTECTED = 9
    FILE_NOT_FOUND = 10


# Files only activation may write: a direct CreateFile/Remove/Truncate would bypass the loader's
# validation. The robot's own state files and the layout directories are off limits too (a directory
# created at params.json's name would make every later save raise).
PROTECTED = frozenset({ACTIVE_POLICY, LAST_GOOD_POLICY, ACTIVE_MAP, LAST_GOOD_MAP, PARAMS_FILE, UID_FILE, "/" + SIGNING_FILE, *LAYOUT_DIRS,
                       GENERAL_FILE, PARAMETER_FILE, METADATA_DIR})
# Folders read-only over FTP, everything in them too: the robot's own log is written through an open
# file handle (a change there would lose records until the next rotation), and the component metadata
# folder is the robot's own. Reading and listing stay allowed.
READ_ONLY_DIRS = ("/" + LOG_DIR, METADATA_DIR)


@dataclass
class Request:
    seq: int
    session: int
    opcode: int
    size: int
    offset: int
    data: bytes


Owner = tuple[int, int]  # (sysid, compid) of the client
LOCAL_OWNER: Owner = (0, 0)  # requests without a MAVLink source (tests, a local shell)


@dataclass
class _Session:
    sid: int
    path: str
    last_us: int
    fd: int = -1  # open for reading
    file_size: int = 0
    upload: Upload | None = None  # open for writing


@dataclass
class FtpStats:
    requests: int = 0
    naks: int = 0
    retries_answered_from_cache: int = 0
    malformed: int = 0
    expired_sessions: int = 0
    evicted_sessions: int = 0
    foreign_session_requests: int = 0  # a request on a session id another client owns
    commits: int = 0
    activations: int = 0
    refusals: int = 0


def pack(seq: int, session: int, opcode: int, req_opcode: int, offset: int,
         data: bytes = b"", burst_complete: int = 0) -> bytes:
    """One FTP payload (header + data, unpadded)."""
    return HEADER.pack(seq & 0xFFFF, session, opcode, len(data), req_opcode,
                       burst_complete, 0, offset & 0xFFFFFFFF) + data


def parse(payload: bytes) -> tuple[int, int, int, int, int, int, int, bytes]:
    """(seq, session, opcode, size, req_opcode, burst_complete, offset, data[:size])."""
    seq, session, opcode, size, req_opcode, burst, _pad, offset = HEADER.unpack_from(payload, 0)
    return seq, session, opcode, size, req_opcode, burst, offset, bytes(payload[HEADER.size:HEADER.size + size])


_ERRNO_NAKS = {errno.ENOENT: Nak.FILE_NOT_FOUND, errno.ENOTDIR: Nak.FILE_NOT_FOUND, errno.EEXIST: Nak.FILE_EXISTS,
               errno.EACCES: Nak.FILE_PROTECTED, errno.EPERM: Nak.FILE_PROTECTED, errno.ELOOP: Nak.FILE_PROTECTED}


def _errno_nak(exc: OSError) -> tuple[Nak, bytes]:
    """NAK code and extra data for a storage error."""
    code = exc.errno or 0
    if code in _ERRNO_NAKS:
        return _ERRNO_NAKS[code], b""
    if 0 < code < 256:
        return Nak.FAIL_ERRNO, bytes([code])
    return Nak.FAIL, b""


@dataclass(frozen=True)
class _Slot:
    """What a Rename onto an active file activates: a policy or the robot's map."""

    what: str  # "policy" | "map": in the STATUSTEXTs
    active: str
    last_good: str


POLICY_SLOT = _Slot("policy", ACTIVE_POLICY, LAST_GOOD_POLICY)
MAP_SLOT = _Slot("map", ACTIVE_MAP, LAST_GOOD_MAP)


@dataclass
class _PendingRename:
    """A Rename onto the active policy whose activation runs off the link
    thread: answered (to the newest retry) by `FtpServer.poll` when done."""

    owner: Owner
    req: Request
    path: str  # the renamed file, normalised
    src: Any  # its host path
    activation: Any  # vehicle.PendingActivation
    since_us: int
    slot: _Slot = POLICY_SLOT


# a file up to this size is summed on the link thread (a worker's reply would wait for the link
# thread's next slot, a control period, and an upload asks for CRCs often); larger ones off it
INLINE_CRC_BYTES = 1 << 20


@dataclass
class _Offloaded:
    """File work running on the offload worker; `poll` answers `req` (the newest retry) when done."""

    owner: Owner
    req: Request
    what: tuple[int, str]  # (opcode, path): what a retry is recognised by
    key: bytes = b""  # the request's bytes, for the retry cache once answered
    done: bool = False
    value: bytes = b""  # the ACK's data
    error: BaseException | None = None


class FtpServer:
    """See the module docstring. `activate(host_path)` is the vehicle's `begin_activation`: (ok,
    reason), or a pending activation whose reply `poll` sends when it is done (a retried Rename
    meanwhile gets none); None refuses every activation."""

    def __init__(self, storage: Storage, activate: Callable[[str], Any] | None = None,
                 *, activate_map: Callable[[str], Any] | None = None, max_sessions: int = 4, session_timeout_us: int = 5_000_000,
                 burst_max_packets: int = 64, max_sessions_per_client: int = 2,
                 evict_idle_us: int = 1_000_000,
                 activation_timeout_us: int = round(ACTIVATION_TIMEOUT_S * 1_000_000),
                 offload: Background | None = None) -> None:
        self.storage = storage
        self.activate = activate
        self.activate_map = activate_map  # the vehicle's `begin_map_activation` (a rename onto /maps/active.map)
        self.offload = offload
        self._offloaded: list[_Offloaded] = []
        self.activation_timeout_us = activation_timeout_us
        self._pending: _PendingRename | None = None
        self.max_sessions = max_sessions
        self.max_sessions_per_client = max_sessions_per_client
        self.session_timeout_us = session_timeout_us
        self.evict_idle_us = evict_idle_us
        self.burst_max_packets = burst_max_packets
        self.sessions: dict[tuple[Owner, int], _Session] = {}
        # (owner, session) -> (request, replies, t)
        self._cache: dict[tuple[Owner, int], tuple[bytes, list[bytes], int]] = {}
        self._owner: Owner = LOCAL_OWNER  # of the request being handled
        self._request_key = b""  # and its bytes (the retry cache's key)
        self._texts: list[tuple[int, str]] = []
        self.stats = FtpStats()

    # --- public ------------------------------------------------------------------
    def handle(self, payload: bytes | bytearray, now_us: int, owner: Owner = LOCAL_OWNER) -> list[bytes]:
        """Process one request payload from `owner` (sysid, compid); return the reply payloads."""
        self.expire(now_us)
        self._owner = owner
        payload = bytes(payload)
        if len(payload) < HEADER.size:
            self.stats.malformed += 1
            return []  # no header, nothing to address a reply to
        seq, session, opcode, size, _req, _burst, _pad, offset = HEADER.unpack_from(payload, 0)
        if opcode in (Op.ACK, Op.NAK):
            return []  # a reply, not a request (another server on the link)
        self.stats.requests += 1
        key = payload[:HEADER.size + min(size, MAX_DATA)]
        cached = self._cache.get((owner, session))
        if (cached is not None and cached[0] == key and now_us - cached[2] <= self.session_timeout_us
                and opcode != Op.BURST_READ_FILE):
            self.stats.retries_answered_from_cache += 1
            return list(cached[1])
        req = Request(seq, session, opcode, size, offset, payload[HEADER.size:HEADER.size + size])
        self._request_key = key
        if size > MAX_DATA or size > len(payload) - HEADER.size:
            self.stats.malformed += 1
            replies = [self._nak(req, Nak.INVALID_DATA_SIZE)]
        else:
            replies = self._dispatch(req, now_us)
        if opcode == Op.RESET_SESSIONS:
            for k in [k for k in self._cache if k[0] == owner]:
                del self._cache[k]
        elif opcode != Op.BURST_READ_FILE:
            self._cache[(owner, session)] = (key, replies, now_us)
        return replies

    def expire(self, now_us: int) -> None:
        """Close sessions idle longer than the timeout (uncommitted writes dropped)."""
        for key, s in list(self.sessions.items()):
            if now_us - s.last_us > self.session_timeout_us:
                self._close(key, commit=False)
                self.stats.expired_sessions += 1
        for key, (_k, _r, t) in list(self._cache.items()):
            if now_us - t > self.session_timeout_us:
                del self._cache[key]

    def poll(self, now_us: int) -> list[tuple[Owner, bytes]]:
        """(owner, reply) of offloaded file work and of a pending activation that finished (or timed out)."""
        out = self._poll_offloaded(now_us)
        p = self._pending
        if p is None:
            return out
        got = p.activation.result()
        if got is None:
            if now_us - p.since_us <= self.activation_timeout_us:
                return out
            if p.activation.cancel() is False:  # the worker is swapping it in right now: its result stands
                return out
            got = (False, f"activation not ready within {self.activation_timeout_us / 1e6:g} s")
        self._pending = None
        ok, reason = got
        if ok:
            try:
                commit_promotion(self.storage, p.src, p.slot.active, p.slot.last_good)
            except OSError as exc:  # the policy runs; its file stays under its own name
                ok, reason = False, f"active, but its file was not kept: {exc}"
        reply = self._finish_activation(p.req, p.path, ok, reason, p.slot)
        self._cache[(p.owner, p.req.session)] = (b"", [reply], now_us)
        return out + [(p.owner, reply)]

    def _poll_offloaded(self, now_us: int) -> list[tuple[Owner, bytes]]:
        out = []
        for job in [j for j in self._offloaded if j.done]:
            self._offloaded.remove(job)
            if job.error is None:
                reply = self._ack(job.req, job.value)
            elif isinstance(job.error, OSError):
                reply = self._nak_os(job.req, job.error)
            else:
                reply = self._nak(job.req, Nak.FAIL)
            self._cache[(job.owner, job.req.session)] = (job.key, [reply], now_us)
            out.append((job.owner, reply))
        return out

    def _offload(self, req: Request, what: tuple[int, str], work: Callable[[], bytes]) -> list[bytes]:
        """Run `work` (the ACK's data; may raise) on the offload worker; `poll` answers."""
        for job in self._offloaded:
            if job.owner == self._owner and job.what == what and job.req.session == req.session:
                job.req = req  # a retry: answered when the work is done
                return []
        job = _Offloaded(self._owner, req, what, self._request_key)

        def run() -> None:
            try:
                job.value = work()
            except Exception as exc:  # answered as a NAK by poll, never raised on the link thread
                job.error = exc
            job.done = True

        self._offloaded.append(job)
        assert self.offload is not None
        self.offload.post(job, run)
        return []

    def drain_texts(self) -> list[tuple[int, str]]:
        """(severity, text) messages for STATUSTEXT since the last call."""
        out, self._texts = self._texts, []
        return out

    def close(self, owner: Owner | None = None) -> None:
        """Drop every session of `owner` (None: of everyone); uncommitted writes discarded."""
        for key in list(self.sessions):
            if owner is None or key[0] == owner:
                self._close(key, commit=False)

    # --- helpers -----------------------------------------------------------------
    def _ack(self, req: Request, data: bytes = b"", offset: int | None = None) -> bytes:
        return pack(req.seq + 1, req.session, Op.ACK, req.opcode,
                    req.offset if offset is None else offset, data)

    def _nak(self, req: Request, code: Nak, extra: bytes = b"") -> bytes:
        self.stats.naks += 1
        return pack(req.seq + 1, req.session, Op.NAK, req.opcode, req.offset, bytes([code]) + extra)

    def _nak_os(self, req: Request, exc: OSError) -> bytes:
        return self._nak(req, *_errno_nak(exc))

    @staticmethod
    def _path(req: Request) -> str:
        raw = req.data.split(b"\0", 1)[0]
        return raw.decode("utf-8")  # UnicodeDecodeError is a ValueError -> NAK Fail

    @staticmethod
    def _norm(path: str) -> str:
        return "/" + "/".join(p for p in path.split("/") if p not in ("", "."))

    def _close(self, key: tuple[Owner, int], commit: bool) -> None:
        s = self.sessions.pop(key, None)
        if s is None:
            return
        if s.fd >= 0:
            os.close(s.fd)
        if s.upload is not None:
            if commit:
                s.upload.commit()
                self.stats.commits += 1
            else:
                s.upload.abort()

    def _key(self, req: Request) -> tuple[Owner, int]:
        return (self._owner, req.session)

    def _open_session(self, req: Request, now_us: int) -> _Session | bytes:
        """A fresh session numbered like the request, or a NAK."""
        key = self._key(req)
        if key in self.sessions:
            self._close(key, commit=False)  # the client reused its id: the old one is dead
        if sum(1 for k in self.sessions if k[0] == self._owner) >= self.max_sessions_per_client:
            return self._nak(req, Nak.NO_SESSIONS_AVAILABLE)
        if len(self.sessions) >= self.max_sessions:
            idle = min(self.sessions.items(), key=lambda kv: kv[1].last_us)
            if now_us - idle[1].last_us <= self.evict_idle_us:
                return self._nak(req, Nak.NO_SESSIONS_AVAILABLE)
            self._close(idle[0], commit=False)  # least recently used and idle: it yields
            self.stats.evicted_sessions += 1
        return _Session(req.session, "", now_us)

    def _session(self, req: Request, now_us: int, writing: bool) -> _Session | None:
        s = self.sessions.get(self._key(req))
        if s is None and any(k[1] == req.session for k in self.sessions):
            self.stats.foreign_session_requests += 1
        if s is None or (s.upload is not None) != writing:
            return None
        s.last_us = now_us
        return s

    def _protected(self, path: str) -> bool:
        norm = self._norm(path)
        return norm in PROTECTED or any(norm == d or norm.startswith(d + "/") for d in READ_ONLY_DIRS)

    # --- dispatch ------------------------------------------------------------------
    def _dispatch(self, req: Request, now_us: int) -> list[bytes]:
        handler = self._HANDLERS.get(req.opcode)
        if handler is None:
            return [self._nak(req, Nak.UNKNOWN_COMMAND)]
        try:
            out = handler(self, req, now_us)
        except OSError as exc:
            return [self._nak_os(req, exc)]
        except ValueError:  # undecodable path, bad rename payload
            return [self._nak(req, Nak.FAIL)]
        return out if isinstance(out, list) else [out]

    def _op_terminate(self, req: Request, now_us: int) -> bytes | list[bytes]:
        if self._key(req) not in self.sessions:
            if any(k[1] == req.session for k in self.sessions):
                self.stats.foreign_session_requests += 1
            return self._nak(req, Nak.INVALID_SESSION)
        if self.offload is None:
            self._close(self._key(req), commit=True)
            return self._ack(req)
        s = self.sessions.pop(self._key(req))  # the session ends now; its file is committed off this thread
        if s.fd >= 0:
            os.close(s.fd)
        upload = s.upload
        if upload is None:
            return self._ack(req)
        self.stats.commits += 1

        def commit() -> bytes:
            upload.commit()
            return b""
        return self._offload(req, (Op.TERMINATE_SESSION, str(upload.final)), commit)

    def _op_reset(self, req: Request, now_us: int) -> bytes:
        self.close(self._owner)
        return self._ack(req)

    def _op_list(self, req: Request, now_us: int) -> bytes:
        with_time = req.opcode == Op.LIST_DIRECTORY_WITH_TIME
        entries = self.storage.listdir(self._path(req))
        if req.offset >= len(entries):
            return self._nak(req, Nak.EOF)
        out = b""
        for e in entries[req.offset:]:
            if e.is_dir:
                text = f"D{e.name}\t0\t{e.mtime}" if with_time else f"D{e.name}"
            else:
                text = f"F{e.name}\t{e.size}\t{e.mtime}" if with_time else f"F{e.name}\t{e.size}"
            item = text.encode("utf-8", "replace") + b"\0"
            if len(out) + len(item) > MAX_DATA:
                break
            out += item
        if not out:  # one entry too long for a packet: skip it rather than loop forever
            return self._nak(req, Nak.FAIL)
        return self._ack(req, out)

    def _op_open_ro(self, req: Request, now_us: int) -> bytes:
        path = self._path(req)
        fd, size = self.storage.open_read(path)
        s = self._open_session(req, now_us)
        if isinstance(s, bytes):
            os.close(fd)
            return s
        s.path, s.fd, s.file_size = path, fd, size
        self.sessions[self._key(req)] = s
        return self._ack(req, struct.pack("<I", size & 0xFFFFFFFF))

    def _open_write(self, req: Request, now_us: int, keep: bool) -> bytes:
        path = self._path(req)
        if self._protected(path):
            return self._nak(req, Nak.FILE_PROTECTED)
        s = self._open_session(req, now_us)
        if isinstance(s, bytes):
            return s
        s.path, s.upload = path, self.storage.begin_write(path, keep_contents=keep)
        self.sessions[self._key(req)] = s
        if keep:
            return self._ack(req, struct.pack("<I", s.upload.size & 0xFFFFFFFF))
        return self._ack(req)

    def _read_chunk(self, s: _Session, offset: int, size: int) -> bytes:
        n = MAX_DATA if size == 0 or size > MAX_DATA else size
        return os.pread(s.fd, n, offset)

    def _op_read(self, req: Request, now_us: int) -> bytes:
        s = self._session(req, now_us, writing=False)
        if s is None:
            return self._nak(req, Nak.INVALID_SESSION)
        if req.offset >= s.file_size:
            return self._nak(req, Nak.EOF)
        return self._ack(req, self._read_chunk(s, req.offset, req.size))

    def _op_burst(self, req: Request, now_us: int) -> list[bytes]:
        s = self._session(req, now_us, writing=False)
        if s is None:
            return [self._nak(req, Nak.INVALID_SESSION)]
        if req.offset >= s.file_size:
            return [self._nak(req, Nak.EOF)]
        chunk_size = MAX_DATA if req.size == 0 or req.size > MAX_DATA else req.size
        out = []
        offset = req.offset
        for i in range(self.burst_max_packets):
            data = self._read_chunk(s, offset, chunk_size)
            last = (i == self.burst_max_packets - 1 or len(data) < chunk_size
                    or offset + len(data) >= s.file_size)
            out.append(pack(req.seq + 1 + i, req.session, Op.ACK, req.opcode, offset, data,
                            burst_complete=1 if last else 0))
            offset += len(data)
            if last:
                break
        return out

    def _op_write(self, req: Request, now_us: int) -> bytes:
        s = self._session(req, now_us, writing=True)
        if s is None:
            return self._nak(req, Nak.INVALID_SESSION)
        assert s.upload is not None
        s.upload.write(req.offset, req.data)
        return self._ack(req)

    def _change(self, req: Request, change: Callable[[str], object]) -> bytes:
        """Apply `change` to the request's path: NAK FileProtected on the robot's active
        files, else ACK once it is done (an OSError NAKs in `_dispatch`)."""
        path = self._path(req)
        if self._protected(path):
            return self._nak(req, Nak.FILE_PROTECTED)
        change(path)
        return self._ack(req)

    def _op_truncate(self, req: Request, now_us: int) -> bytes:
        return self._change(req, lambda path: self.storage.truncate(path, req.offset))

    def _op_rename(self, req: Request, now_us: int) -> bytes | list[bytes]:
        parts = req.data.split(b"\0")
        if len(parts) < 2 or not parts[0] or not parts[1]:
            return self._nak(req, Nak.FAIL)
        old, new = parts[0].decode("utf-8"), parts[1].decode("utf-8")
        if self._protected(old):
            return self._nak(req, Nak.FILE_PROTECTED)
        if self._norm(new) == ACTIVE_POLICY:
            return self._activate(req, old, now_us, POLICY_SLOT)
        if self._norm(new) == ACTIVE_MAP:
            return self._activate(req, old, now_us, MAP_SLOT)
        if self._protected(new):
            return self._nak(req, Nak.FILE_PROTECTED)
        self.storage.rename(old, new)
        return self._ack(req)

    def _activate(self, req: Request, old: str, now_us: int, slot: _Slot) -> bytes | list[bytes]:
        path = self._norm(old)
        pending = self._pending
        if pending is not None:
            if (pending.owner, pending.path) == (self._owner, path):
                pending.req = req  # a retry: the reply, when it comes, answers this one
                return []
            return self._finish_activation(req, path, False, f"activation of {pending.path} in progress", slot)
        hook = self.activate if slot is POLICY_SLOT else self.activate_map
        if hook is None:
            return self._finish_activation(req, path, False, f"no vehicle attached to activate a {slot.what}", slot)
        try:
            got = promote_policy(self.storage, old, hook, slot.active, slot.last_good)
        except OSError:
            raise
        except Exception as exc:  # a hook that raises is a refusal, never a crash of the link
            got = (False, f"{type(exc).__name__}: {exc}")
        if not isinstance(got, tuple):  # built off this thread; `poll` answers when it is done
            self._pending = _PendingRename(self._owner, req, path, policy_source(self.storage, old, slot.active),
                                           got, now_us, slot)
            return []
        ok, reason = got
        return self._finish_activation(req, path, ok, reason, slot)

    def _finish_activation(self, req: Request, path: str, ok: bool, reason: str, slot: _Slot) -> bytes:
        if not ok:
            self.stats.refusals += 1
            self._texts.append((SEVERITY_WARNING, f"{slot.what} refused: {reason}"))
            return self._nak(req, Nak.FAIL)
        self.stats.activations += 1
        self._texts.append((SEVERITY_INFO, f"{slot.what} active: {reason or path}"))
        return self._ack(req)

    def _op_crc(self, req: Request, now_us: int) -> bytes | list[bytes]:
        path = self._path(req)
        if self.offload is None or self.storage.size(path) <= INLINE_CRC_BYTES:
            return self._ack(req, struct.pack("<I", self.storage.crc32(path)))
        return self._offload(req, (Op.CALC_FILE_CRC32, path), lambda: struct.pack("<I", self.storage.crc32(path)))

    _HANDLERS: dict[int, Callable[[FtpServer, Request, int], bytes | list[bytes]]] = {
        Op.TERMINATE_SESSION: _op_terminate,
        Op.RESET_SESSIONS: _op_reset,
        Op.LIST_DIRECTORY: _op_list,
        Op.OPEN_FILE_RO: _op_open_ro,
        Op.READ_FILE: _op_read,
        Op.CREATE_FILE: functools.partial(_open_write, keep=False),
        Op.WRITE_FILE: _op_write,
        Op.REMOVE_FILE: lambda self, req, _now: self._change(req, self.storage.remove),
        Op.CREATE_DIRECTORY: lambda self, req, _now: self._change(req, self.storage.mkdir),
        Op.REMOVE_DIRECTORY: lambda self, req, _now: self._change(req, self.storage.rmdir),
        Op.OPEN_FILE_WO: functools.partial(_open_write, keep=True),
        Op.TRUNCATE_FILE: _op_truncate,
        Op.RENAME: _op_rename,
        Op.CALC_FILE_CRC32: _op_crc,
        Op.BURST_READ_FILE: _op_burst,
        Op.LIST_DIRECTORY_WITH_TIME: _op_list,
    }
