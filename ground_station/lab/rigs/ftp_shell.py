"""Thin shell around `FtpServer`: FILE_TRANSFER_PROTOCOL in, replies out, on a
pymavlink connection.

The MAVLink node (`firmware_py.mavlink.node`) hands every FILE_TRANSFER_PROTOCOL
message to `FtpLink.handle_message`. Standalone (`python -m
ground_station.lab.rigs.ftp_shell --root DIR --mavlink udpin:127.0.0.1:PORT`) it also
sends a 1 Hz HEARTBEAT so stock clients (`python -m pymavlink.mavftp`,
MAVProxy) find the robot; tests and `qnav bench upload` use that mode, started as a child process by
`robot_ftp_process`. The
standalone activation hook only validates the file with the policy loader
(there is no vehicle); the real robot passes `VehicleControl.activate_policy`.

Signing: pass a 32-byte key (`firmware_py.mavlink.signing.load_key_file`: raw, hex
or passphrase, as the MAVLink node reads it); the connection then signs
everything it sends and drops unsigned input. MAVLINK20=1 must be in the
environment before pymavlink is imported, or pymavlink's later switch to
MAVLink 2 throws the signing setup away (design.md section 3).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from firmware_py.clock import Clock, WallClock
from firmware_py.mavlink.ftp_server import PAYLOAD_LEN, FtpServer
from firmware_py.mavlink.signing import load_key_file
from firmware_py.storage import DEFAULT_QUOTA_BYTES, Storage
from ground_station.processes import ChildProcess, program_argv

if TYPE_CHECKING:  # annotations only: pymavlink is imported after MAVLINK20 is set (see above)
    from pymavlink import mavutil

    from firmware_py.mavlink.dialect import mavlink2

STATUSTEXT_CHARS = 50
MAV_TYPE_GROUND_ROVER = 10
MAV_AUTOPILOT_GENERIC = 0


def validate_only_activate(path: str) -> tuple[bool, str]:
    """Standalone activation hook: accept exactly what the policy loader accepts."""
    from firmware_py.policy import PolicyError, load_policy

    try:
        pol = load_policy(path)
    except PolicyError as exc:
        return False, str(exc)
    return True, f"id 0x{pol.policy_id:08x}"


class FtpLink:
    """Serves `server` on the pymavlink connection `conn`."""

    def __init__(self, conn: mavutil.mavfile, server: FtpServer, clock: Clock, *, sysid: int = 1, compid: int = 1) -> None:
        self.conn = conn
        self.server = server
        self.clock = clock
        self.sysid = sysid
        self.compid = compid
        self._statustext_id = 0

    def handle_message(self, msg: mavlink2.MAVLink_message) -> None:
        """Serve one FILE_TRANSFER_PROTOCOL message addressed to us (or broadcast)."""
        if msg.target_system not in (0, self.sysid) or msg.target_component not in (0, self.compid):
            return
        dst_sys, dst_comp = msg.get_srcSystem(), msg.get_srcComponent()
        replies = self.server.handle(bytes(msg.payload), self.clock.now_us(), (dst_sys, dst_comp))
        self._send(replies, dst_sys, dst_comp)

    def _send(self, replies: list[bytes], dst_sys: int, dst_comp: int) -> None:
        for severity, text in self.server.drain_texts():
            self.send_statustext(severity, text)
        for r in replies:
            payload = bytearray(r) + bytearray(PAYLOAD_LEN - len(r))
            self.conn.mav.file_transfer_protocol_send(0, dst_sys, dst_comp, payload)

    def send_statustext(self, severity: int, text: str) -> None:
        """STATUSTEXT, split into 50-char chunks sharing an id when longer."""
        data = text.encode("utf-8", "replace")
        chunks = [data[i:i + STATUSTEXT_CHARS] for i in range(0, max(len(data), 1), STATUSTEXT_CHARS)]
        if len(chunks) == 1:
            self.conn.mav.statustext_send(severity, chunks[0])
            return
        self._statustext_id = self._statustext_id % 65535 + 1
        if len(chunks[-1]) == STATUSTEXT_CHARS:
            chunks.append(b"")  # a full last chunk needs an empty terminator
        for i, c in enumerate(chunks):
            self.conn.mav.statustext_send(severity, c, self._statustext_id, i)

    def serve(self, stop: threading.Event, heartbeat: bool = True,
              on_idle: Callable[[], None] | None = None) -> None:
        """Standalone loop: receive, serve, heartbeat at 1 Hz, expire sessions."""
        next_hb = 0.0
        while not stop.is_set():
            now = time.monotonic()
            if heartbeat and now >= next_hb:
                self.conn.mav.heartbeat_send(MAV_TYPE_GROUND_ROVER, MAV_AUTOPILOT_GENERIC, 0, 0, 0)
                next_hb = now + 1.0
            msg = self.conn.recv_match(type="FILE_TRANSFER_PROTOCOL", blocking=True, timeout=0.05)
            if msg is not None:
                self.handle_message(msg)
            else:
                self.server.expire(self.clock.now_us())
                for owner, reply in self.server.poll(self.clock.now_us()):
                    self._send([reply], *owner)
                if on_idle is not None:
                    on_idle()


def open_link(root: str, url: str, *, signing_key: bytes | None = None, quota: int = DEFAULT_QUOTA_BYTES,
              activate: Callable[[str], tuple[bool, str]] | None = validate_only_activate,
              sysid: int = 1, compid: int = 1) -> FtpLink:
    """Build storage + server + pymavlink connection for standalone serving."""
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(url, source_system=sysid, source_component=compid)
    if signing_key is not None:
        conn.setup_signing(signing_key, sign_outgoing=True, allow_unsigned_callback=None, link_id=0)
    from firmware_py.background import Background

    server = FtpServer(Storage(root, quota_bytes=quota), activate=activate, offload=Background())
    return FtpLink(conn, server, WallClock(), sysid=sysid, compid=compid)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m ground_station.lab.rigs.ftp_shell",
        description="Serve the robot's MAVLink FTP storage on its own (no controller): "
                    "for tests, benchmarks and bench bring-up.")
    p.add_argument("--root", required=True, help="storage root directory (created if missing)")
    p.add_argument("--mavlink", default="udpin:127.0.0.1:14551",
                   help="pymavlink connection string (default %(default)s)")
    p.add_argument("--signing-key", help="MAVLink 2 signing key file (32 bytes, 64 hex digits or a passphrase)")
    p.add_argument("--quota", type=int, default=DEFAULT_QUOTA_BYTES, help="storage quota in bytes")
    p.add_argument("--no-validate", action="store_true",
                   help="accept any file on activation (default: the policy loader decides)")
    args = p.parse_args(argv)
    key = None
    if args.signing_key:
        try:
            key = load_key_file(args.signing_key)
        except ValueError as exc:
            print(f"ftp_link: error: {exc}", file=sys.stderr)
            return 2
    activate = (lambda path: (True, "not validated")) if args.no_validate else validate_only_activate
    link = open_link(args.root, args.mavlink, signing_key=key, quota=args.quota, activate=activate)
    print(f"ftp_link: serving {link.server.storage.root} on {args.mavlink}", flush=True)
    stop = threading.Event()
    try:
        link.serve(stop)
    except KeyboardInterrupt:
        pass
    finally:
        link.server.close()
        link.conn.close()
    return 0



@contextlib.contextmanager
def robot_ftp_process(root: Path, url: str, key_file: Path | None = None, extra: list[str] | None = None,
                      log: Path | None = None) -> Iterator[subprocess.Popen]:
    """The robot's standalone FTP shell in a child process, once it serves; always stopped on
    exit. Its output goes to `log` (default: root/../<root name>.log)."""
    args = ["--root", str(root), "--mavlink", url]
    if key_file is not None:
        args += ["--signing-key", str(key_file)]
    child = ChildProcess([*program_argv("ground_station.lab.rigs.ftp_shell:main", "qnav-ftp-shell"), *args, *(extra or [])],
                         log or root.parent / f"{root.name}.log")
    proc = child.start().proc
    assert proc is not None
    try:
        deadline = time.monotonic() + 20
        while "serving" not in child.log_text():  # printed once the socket is up
            if not child.alive or time.monotonic() > deadline:
                raise RuntimeError(f"robot FTP shell did not start: {child.log_text().strip()}")
            time.sleep(0.05)
        yield proc
    finally:
        child.stop(grace_s=5.0)

if __name__ == "__main__":
    sys.exit(main())
