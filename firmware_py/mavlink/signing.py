"""MAVLink 2 message signing on the robot: key, input filter, timestamps.

Owns the signing key (provisioned by SETUP_SIGNING or a key file), the decision whether an incoming
frame is accepted, the drop counters, and the persisted signing state (`<storage>/signing.json`: key
set by SETUP_SIGNING, last timestamp, per-stream timestamps) so replays are refused across reboots
too. The file is under the FTP root, but FTP is refused unsigned whenever a key is set, so only a
key holder can read it.

The rules (as ArduPilot's, plus the bounds FUTURE_WINDOW, MAX_TIMESTAMP, `replay_floor` after a
boot) are in docs/mavlink.md, "Signing". The verification is done here rather than by pymavlink's
parser so the counters and the new-stream and persistence rules are ours. pymavlink still signs
outgoing frames (the shell copies `key`/`timestamp`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

from firmware_py.atomic import atomic_write

if TYPE_CHECKING:  # only for the annotation: the filter works on any message's raw frame
    from firmware_py.mavlink.dialect import mavlink2

SIGNING_FILE = "params/signing.json"  # under the storage root, beside params.json
EPOCH_2015_UNIX_S = 1_420_070_400
NEW_STREAM_SLACK = 60 * 100_000  # one minute in 10 us units
FUTURE_WINDOW = 60 * 100_000  # a frame may be at most one minute ahead of the robot's timestamp
MAX_TIMESTAMP = (1 << 48) - 1  # the signature's timestamp field is 48 bits
PERSIST_INTERVAL_US = 10_000_000
MAX_STREAMS = 64
MSG_ID_RADIO_STATUS = 109
UNSIGNED_ALLOWED = frozenset({MSG_ID_RADIO_STATUS})
_SIGNED_FLAG = 0x01


def wall_timestamp() -> int:
    """Signing timestamp of the host's wall clock (10 us since 2015), >= 0."""
    return max(0, int((time.time() - EPOCH_2015_UNIX_S) * 100_000))


def load_key_file(path: str | os.PathLike[str]) -> bytes:
    """Read a signing key file: 32 raw bytes, 64 hex characters, or a text
    passphrase (key = sha256(passphrase), as MAVProxy's `signing setup`)."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read signing key file {path}: {exc.strerror}") from exc
    text = data.strip()
    if len(data) == 32 and not text.isascii():
        return data
    if not text:
        raise ValueError(f"signing key file {path} is empty")
    try:
        decoded = text.decode()
    except UnicodeDecodeError as exc:
        raise ValueError(f"signing key file {path}: not 32 raw bytes, hex or a text passphrase") from exc
    if len(decoded) == 64:
        with contextlib.suppress(ValueError):  # 64 characters but not hex: a passphrase
            return bytes.fromhex(decoded)
    return hashlib.sha256(decoded.encode()).digest()


class Signing:
    """Signing state and input filter (a pure engine: no I/O but its file)."""

    def __init__(self, storage_dir: str | os.PathLike[str] | None = None) -> None:
        self.path = Path(storage_dir) / SIGNING_FILE if storage_dir is not None else None
        self.key: bytes | None = None
        self.require = True
        self.timestamp = 0  # highest timestamp sent or accepted
        self.streams: dict[tuple[int, int, int], int] = {}
        self.accepted_unsigned = 0
        self.dropped_unsigned = 0
        self.dropped_badsig = 0
        self.dropped_replay = 0
        self.dropped_future = 0
        self.replay_floor = 0  # no frame older than the boot timestamp (see module doc)
        self.key_version = 0  # bumped on every key change; the shell re-applies it
        self._boot_ts = 0
        self._boot_us = 0
        self._dirty = False
        self._last_persist_us = 0
        self._key_from_file = False
        self.last_signed = False  # was the last accepted frame validly signed

    @property
    def dropped(self) -> int:
        return self.dropped_unsigned + self.dropped_badsig + self.dropped_replay + self.dropped_future

    # --- boot ---------------------------------------------------------------
    def load(self, now_us: int, key_file: str | os.PathLike[str] | None = None) -> list[str]:
        """Restore the persisted state, then the key file (it wins over a
        stored key). Raises ValueError only for an unreadable key file."""
        warnings: list[str] = []
        self.key, self.streams, stored_ts = None, {}, 0
        if self.path is not None and self.path.exists():
            try:
                doc = json.loads(self.path.read_text())
                stored_ts = int(doc.get("timestamp", 0))
                if doc.get("key"):
                    key = bytes.fromhex(doc["key"])
                    if len(key) != 32:
                        raise ValueError("key is not 32 bytes")
                    self.key = key
                for link, sysid, compid, ts in doc.get("streams", []):
                    self.streams[(int(link), int(sysid), int(compid))] = int(ts)
            except (OSError, ValueError, TypeError, AttributeError) as exc:
                warnings.append(f"signing state corrupt ({exc}); key and timestamps reset")
                self.key, self.streams, stored_ts = None, {}, 0
        wall = wall_timestamp()
        ceiling = min(MAX_TIMESTAMP, wall + FUTURE_WINDOW) if wall > 0 else MAX_TIMESTAMP
        if stored_ts > ceiling or any(ts > ceiling for ts in self.streams.values()):
            # written by an older robot that let a frame push it towards 2^48: unusable
            warnings.append("signing timestamps beyond the bound; timestamps reset to the clock")
            stored_ts = 0
            self.streams = {k: v for k, v in self.streams.items() if v <= ceiling}
        self._key_from_file = key_file is not None
        if key_file is not None:
            self.key = load_key_file(key_file)
        self.timestamp = min(MAX_TIMESTAMP, max(self.timestamp, stored_ts + 1, wall))
        self.replay_floor = self.timestamp
        self._boot_ts, self._boot_us = self.timestamp, now_us
        self._last_persist_us = now_us
        self.key_version += 1
        return warnings

    # --- provisioning ---------------------------------------------------------
    def setup(self, secret_key: bytes, initial_timestamp: int) -> str:
        """Apply SETUP_SIGNING: all-zero key and timestamp 0 disable signing.
        An initial timestamp beyond the window ahead of the robot's is not
        taken (the key is), so provisioning cannot wedge the timestamps."""
        if not any(secret_key) and initial_timestamp == 0:
            self.key = None
            text = "signing disabled"
        else:
            self.key = bytes(secret_key)
            text = "signing key set"
            if int(initial_timestamp) <= min(MAX_TIMESTAMP, self.timestamp + FUTURE_WINDOW):
                self.timestamp = max(self.timestamp, int(initial_timestamp))
            else:
                text = "signing key set; initial timestamp too far ahead, robot clock kept"
        self.streams.clear()
        self._key_from_file = False
        self.key_version += 1
        self.persist()
        return text

    # --- input filter -----------------------------------------------------------
    def accept(self, msg: mavlink2.MAVLink_message) -> bool:
        """True if `msg` (a pymavlink message with its raw frame) may be handled."""
        self.last_signed = False
        if self.key is None:
            return True
        buf = bytes(msg.get_msgbuf())
        signed = len(buf) > 25 and buf[0] == 0xFD and buf[2] & _SIGNED_FLAG
        if not signed:
            if msg.get_msgId() in UNSIGNED_ALLOWED or not self.require:
                self.accepted_unsigned += 1
                return True
            self.dropped_unsigned += 1
            return False
        if hashlib.sha256(self.key + buf[:-6]).digest()[:6] != buf[-6:]:
            self.dropped_badsig += 1
            return False
        ts = int.from_bytes(buf[-12:-6], "little")
        stream = (buf[-13], msg.get_srcSystem(), msg.get_srcComponent())
        last = self.streams.get(stream)
        if ts > min(MAX_TIMESTAMP, self.timestamp + FUTURE_WINDOW):
            self.dropped_future += 1  # would drag the stream (and, before, the robot) towards 2^48
            return False
        if (ts < self.replay_floor or (last is not None and ts <= last)
                or (last is None and ts + NEW_STREAM_SLACK < self.timestamp)):
            self.dropped_replay += 1
            return False
        self.streams[stream] = ts
        if len(self.streams) > MAX_STREAMS:
            del self.streams[min(self.streams, key=self.streams.__getitem__)]
        # the robot's own timestamp is NOT advanced from input: a key holder's
        # bad clock must not ratchet it forwards (see the module doc)
        self.last_signed = True
        self._dirty = True
        return True

    # --- outgoing timestamp and persistence ---------------------------------------
    def current_timestamp(self, now_us: int) -> int:
        """Timestamp to sign with now: never behind boot time + elapsed robot time."""
        self.timestamp = min(MAX_TIMESTAMP, max(self.timestamp,
                                                self._boot_ts + max(0, now_us - self._boot_us) // 10))
        return self.timestamp

    def note_sent(self, timestamp: int) -> None:
        """The shell reports the signer's timestamp after sending."""
        if timestamp > self.timestamp:
            self.timestamp = min(MAX_TIMESTAMP, timestamp)
            self._dirty = True

    def tick(self, now_us: int) -> None:
        """Persist the timestamps every PERSIST_INTERVAL_US while signing."""
        if self.key is not None and self._dirty and now_us - self._last_persist_us >= PERSIST_INTERVAL_US:
            self.persist(now_us)

    def persist(self, now_us: int | None = None) -> None:
        if now_us is not None:
            self._last_persist_us = now_us
        self._dirty = False
        if self.path is None:
            return
        doc = {
            "version": 1,
            "timestamp": min(MAX_TIMESTAMP, self.timestamp),
            # a key from --signing-key stays in its file, not copied here
            "key": self.key.hex() if self.key is not None and not self._key_from_file else "",
            "streams": [[*k, v] for k, v in sorted(self.streams.items())],
        }
        atomic_write(self.path, json.dumps(doc) + "\n", make_parents=True, mode=0o600)
