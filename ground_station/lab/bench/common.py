"""Shared by benchmarks: a plain table on stdout and a JSON file; one timed
upload."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from firmware_py.mavlink.ftp_server import MAX_DATA

# Link budget of an upload (design.md section 3), for the benchmarks and their estimates.
WRITE_BLOCK = 80  # pymavlink MAVFTP default write_size (bytes of file data per WriteFile)
FLOOR_BLOCK = MAX_DATA  # the largest WriteFile (what ftp_put writes)
FRAME_OVERHEAD = 27  # MAVLink 2 header + FTP header + CRC around the data
SIGNATURE = 13


def theoretical_seconds(size: int, signed: bool, bytes_per_s: float = 5760.0, block: int = WRITE_BLOCK) -> float:
    """Link time of the WriteFile frames alone (design.md section 3), in `block`-byte writes:
    80 (pymavlink's) or 239 (the largest: the least time any MAVLink FTP client can take)."""
    blocks = -(-size // block)
    return (size + blocks * (FRAME_OVERHEAD + (SIGNATURE if signed else 0))) / bytes_per_s



def report(name: str, rows: Sequence[tuple[str, object]], result: dict, json_path: str | None) -> None:
    """Print `rows` as a two-column table and write `result` as JSON if asked."""
    width = max(len(k) for k, _ in rows) if rows else 10
    print(f"== qnav bench {name} ==")
    for key, value in rows:
        if isinstance(value, float):
            value = f"{value:,.3f}" if abs(value) < 1000 else f"{value:,.0f}"
        print(f"{key:<{width}}  {value}")
    if json_path:
        from firmware_py.atomic import atomic_write

        atomic_write(json_path, json.dumps(result, indent=2) + "\n", make_parents=True)
        print(f"wrote {json_path}")


def timed_upload(url: str, key_file: Path | None, local: Path, remote: str, root: Path,
                 row: dict[str, Any]) -> None:
    """Upload `local` to `remote` over `url` with the ground station's client and
    fill `row`: seconds from the first FTP request to the CRC verified (None on
    failure, with `error`), put attempts, byte_exact (the file under the robot's
    store `root` equals `local`), success and the ratio to `row["theoretical_s"]`."""
    from ground_station.mavlink.ftp_upload import upload_policy
    from ground_station.mavlink.link import Link, LinkError

    gcs = Link(url, signing_key=key_file, tlog=False)
    try:
        gcs.connect(10.0)
        t0 = time.monotonic()
        res = upload_policy(gcs, local, remote, deadline_s=600, attempts=10)
        row["seconds"] = time.monotonic() - t0
        row["attempts"] = res.put_attempts
    except LinkError as exc:
        row["seconds"] = None
        row["error"] = str(exc)
    finally:
        gcs.close()
    on_robot = root / remote.lstrip("/")
    row["byte_exact"] = on_robot.is_file() and on_robot.read_bytes() == local.read_bytes()
    row["success"] = row["byte_exact"] and row["seconds"] is not None
    row["ratio"] = row["seconds"] / row["theoretical_s"] if row["seconds"] else None
    if "floor_s" in row:
        row["ratio_floor"] = row["seconds"] / row["floor_s"] if row["seconds"] else None
    if gcs.ftp_session is not None and gcs.ftp_session.puts:
        st = gcs.ftp_session.puts[-1]
        row["put"] = {k: getattr(st, k) for k in ("writes_sent", "rounds", "unknown", "solved_lost", "unsolved",
                                                  "blocks")}
