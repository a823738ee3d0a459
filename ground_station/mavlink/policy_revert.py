"""`qnav policy revert`: the robot's last good policy made its active one again, over MAVLink FTP.

The robot keeps two policy slots (firmware_py/storage.py): `/policies/active.qtab`, the one it
runs and boots, and `/policies/last_good.qtab`, the one it ran before the last activation (boot
falls back to it). Both are read-only over FTP (the server's PROTECTED set): only an activation
moves them. So a revert, on a connected `Link`:

1. reads what the robot runs (POLICY_ID_HI/LO) and `/policies/last_good.qtab`, the copy checked
   against the robot's CalcFileCRC32 of the file;
2. puts those bytes back as `/policies/revert.qtab` and activates it with
   `ftp_upload.upload_policy`, so the robot validates, activates or refuses it as any upload; the
   policy it ran moves into last_good.qtab, so a second revert goes forward again.

Raises `LinkError` with the upload's exit codes (3 refused, 4 no answer in time, 5 mismatch).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ground_station.mavlink.ftp_upload import UploadResult, ftp_session, upload_policy
from ground_station.mavlink.link import EXIT_MISMATCH, EXIT_REFUSED, Link, LinkError

LAST_GOOD_POLICY = "/policies/last_good.qtab"  # firmware_py.storage.LAST_GOOD_POLICY
REVERT_REMOTE = "/policies/revert.qtab"  # the copy put back, renamed onto active.qtab


@dataclass
class RevertResult:
    before: int | None  # POLICY_ID the robot ran (None: it serves no parameters)
    last_good: int | None  # policy id of last_good.qtab (None: this ground station cannot load it)
    upload: UploadResult


def _read_last_good(link: Link, wait_s: float) -> bytes:
    """The bytes of the robot's last_good.qtab, checked against the robot's CRC32 of it."""
    from firmware_py.storage import ftp_crc32
    from ground_station.mavlink.robot_map import read_robot_file

    session = ftp_session(link)
    problem = ""
    for _ in range(2):  # a read cut short by a lossy link is read again once
        data = read_robot_file(link, LAST_GOOD_POLICY)
        if data is None:
            raise LinkError(EXIT_REFUSED, f"the robot has no {LAST_GOOD_POLICY}: no earlier policy to go back to "
                                          "(it keeps one once a second policy has been activated)")
        remote = session.remote_crc(LAST_GOOD_POLICY, wait_s)
        if remote == ftp_crc32(data):
            return data
        problem = (f"read {len(data)} B with file CRC32 0x{ftp_crc32(data):08x}, the robot's is "
                   + ("missing" if remote is None else f"0x{remote:08x}"))
    raise LinkError(EXIT_MISMATCH, f"{LAST_GOOD_POLICY} not read intact ({problem})")


def revert_policy(link: Link, *, deadline_s: float = 300.0, attempts: int = 8,
                  on_read: Callable[[int | None, int | None], None] | None = None) -> RevertResult:
    """Make the robot's last good policy active again (module docstring). `on_read(before, last_good)`
    is called once both ids are known, before anything is written. Raises LinkError."""
    from firmware_py.policy import PolicyError, load_policy
    from ground_station.mavlink.robot_map import running_policy_id

    t0 = time.monotonic()
    before = running_policy_id(link) if link.serves_params else None
    data = _read_last_good(link, min(20.0, deadline_s))
    try:
        last_good: int | None = load_policy(data).policy_id
    except PolicyError:
        last_good = None  # the robot judges it: upload_policy reports its refusal
    if before and last_good == before:
        raise LinkError(EXIT_REFUSED, f"the robot already runs policy 0x{before:08x}, the one in {LAST_GOOD_POLICY}: "
                                      "nothing to revert")
    if on_read is not None:
        on_read(before, last_good)
    left = max(1.0, deadline_s - (time.monotonic() - t0))
    with tempfile.TemporaryDirectory(prefix="qnav-revert-") as tmp:
        local = Path(tmp) / "last_good.qtab"
        local.write_bytes(data)
        res = upload_policy(link, local, REVERT_REMOTE, activate=True, deadline_s=left, attempts=attempts)
    return RevertResult(before, last_good, res)
