"""`qnav bench upload --serial`: the policy upload over the emulated serial radio.

The same measurement as `qnav bench upload`
(ground_station/lab/bench/upload.py), with the link a pair of
pseudo-terminals joined by the SiK-like radio emulator
(ground_station/lab/rigs/serial_radio.py, 57600 baud, 10 bits per byte): the
robot's FTP shell opens one end as a serial device, `qnav upload`'s code the
other as `/dev/pts/M,57600`. Per case: seconds from the first FTP request to
the robot's CRC32 verified, the link's time for the WriteFile frames in
80-byte (t80) and 239-byte (t239) writes and the ratios, the packets the
radio lost each way; success = byte-identical on the robot.
"""

from __future__ import annotations

import argparse
import random
import tempfile
from pathlib import Path
from typing import Any

from ground_station.lab.bench.common import FLOOR_BLOCK, theoretical_seconds
from ground_station.lab.rigs.ftp_shell import robot_ftp_process


def run_case(radio: Any, size: int, loss: float, signed: bool, key_file: Path | None, root: Path,
             seed: int) -> dict[str, Any]:
    from ground_station.lab.bench.common import timed_upload

    data = random.Random(seed).randbytes(size)
    remote = f"/policies/serial-{size}-{int(loss * 100)}-{int(signed)}.qtab"
    row: dict[str, Any] = {"size": size, "loss": loss, "signed": signed, "link": "serial",
           "theoretical_s": theoretical_seconds(size, signed, radio.config.bytes_per_s),
           "floor_s": theoretical_seconds(size, signed, radio.config.bytes_per_s, block=FLOOR_BLOCK)}
    with tempfile.TemporaryDirectory() as tmp:
        local = Path(tmp) / f"bench-{size}.qtab"
        local.write_bytes(data)
        up0, down0 = vars(radio.stats.up).copy(), vars(radio.stats.down).copy()
        timed_upload(f"{radio.gcs_device},{radio.config.baud}", key_file, local, remote, root, row)
        row["link_up"] = {k: v - up0[k] for k, v in vars(radio.stats.up).items()}
        row["link_down"] = {k: v - down0[k] for k, v in vars(radio.stats.down).items()}
    return row


def run(args: argparse.Namespace, sizes: list[int], losses: list[float], modes: list[bool]) -> list[dict]:
    """Every (size, signing, loss) case; one radio and one robot FTP shell per loss level and signing."""
    from ground_station.lab.rigs.serial_radio import RadioConfig, SerialRadio

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        key_file = Path(tmp) / "signing.key"
        key_file.write_text(random.Random(args.seed).randbytes(32).hex() + "\n")
        i = 0
        for signed in modes:
            for loss in losses:
                root = Path(tmp) / f"robot-{int(signed)}-{loss}"
                with SerialRadio(RadioConfig(loss=loss, seed=args.seed)) as radio, \
                        robot_ftp_process(root, f"{radio.robot_device},{radio.config.baud}",
                                          key_file if signed else None):
                    for size in sizes:
                        rows.append(run_case(radio, size, loss, signed, key_file if signed else None, root,
                                             args.seed * 1000 + i))
                        i += 1
    return rows
