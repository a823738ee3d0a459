"""`qnav bench upload`: policy upload over an emulated 57600-baud radio.

For 10 KiB and 100 KiB payloads (seeded random bytes of policy size), with
and without MAVLink 2 signing, at 0 / 5 / 20 % frame loss each way (each
frame lost independently, per direction), runs the real path: `qnav
upload`'s code (`ftp_upload.upload_policy`, the `ftp_put` engine) -> link
emulator (ground_station/lab/rigs/link_emulator.py, 5760 B/s each way, 8N1) ->
the robot's FTP shell in its own process (`python -m
ground_station.lab.rigs.ftp_shell`, started by
`ground_station.lab.rigs.ftp_shell.robot_ftp_process`).

Per case: seconds from the first FTP request to the robot's CRC32 verified,
two yardsticks - t80, the WriteFile frames in pymavlink's 80-byte writes
(data + 27 bytes, + 13 signed, at 5760 B/s; issue 16's), and t239, the same
in 239-byte writes (the least any MAVLink FTP client can take) - and the
ratios; the losses the link drew each way; WriteFile frames per block;
success = the file on the robot is byte-identical to the local one.
"""


from __future__ import annotations

import argparse
import random
import tempfile
from pathlib import Path
from typing import Any

from ground_station.lab.bench.common import FLOOR_BLOCK, theoretical_seconds
from ground_station.lab.rigs.ftp_shell import robot_ftp_process
from ground_station.subprocs import free_udp_port


def run_case(size: int, loss: float, signed: bool, key_file: Path | None, robot_port: int, root: Path,
             seed: int) -> dict:
    from ground_station.lab.bench.common import timed_upload
    from ground_station.lab.rigs import link_emulator as emu

    data = random.Random(seed).randbytes(size)
    with tempfile.TemporaryDirectory() as tmp:
        local = Path(tmp) / f"bench-{size}.qtab"
        local.write_bytes(data)
        remote = f"/policies/bench-{size}-{int(loss * 100)}-{int(signed)}.qtab"
        cfg = emu.LinkConfig(loss=loss, seed=seed)
        row: dict[str, Any] = {"size": size, "loss": loss, "signed": signed, "theoretical_s": theoretical_seconds(size, signed),
                               "floor_s": theoretical_seconds(size, signed, block=FLOOR_BLOCK)}
        with emu.LinkEmulator(cfg, robot_peer=("127.0.0.1", robot_port)) as link:
            timed_upload(f"udpout:127.0.0.1:{link.gcs_port}", key_file, local, remote, root, row)
            row["link_up"] = vars(link.stats.up).copy()
            row["link_down"] = vars(link.stats.down).copy()
        log = root.parent / f"{root.name}.log"
        if not row["success"] and log.exists():
            row["robot_log_tail"] = log.read_text()[-2000:]
    return row


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("upload", help="policy upload time over an emulated 57600-baud lossy link",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--json", metavar="FILE", default=None, help="write the result as JSON")
    p.add_argument("--sizes", default="10240,102400", help="payload sizes in bytes (default %(default)s)")
    p.add_argument("--losses", default="0,0.05,0.2", help="frame loss per direction (default %(default)s)")
    p.add_argument("--signing", choices=["both", "off", "on"], default="both", help="signing cases to run")
    p.add_argument("--seed", type=int, default=1, help="link and payload seed (default %(default)s)")
    p.add_argument("--serial", action="store_true",
                   help="over the emulated serial radio (two ptys, 57600 baud; bench/upload_serial.py) instead of UDP")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ground_station.errors import CliError

    try:
        sizes = [int(s) for s in args.sizes.split(",")]
        losses = [float(x) for x in args.losses.split(",")]
    except ValueError as exc:
        raise CliError(f"--sizes/--losses: {exc}") from exc
    modes = {"both": [False, True], "off": [False], "on": [True]}[args.signing]
    if getattr(args, "serial", False):
        from ground_station.lab.bench import upload_serial

        return _table(upload_serial.run(args, sizes, losses, modes), args.json,
                      "emulated serial radio (pty pair), 57600 baud 8N1 = 5760 B/s each way, SiK-like frames")
    cases = [(s, signed, loss) for s in sizes for signed in modes for loss in losses]
    rows = []
    with tempfile.TemporaryDirectory() as tmp, tqdm(total=len(cases), desc="bench upload") as bar:
        key_file = Path(tmp) / "signing.key"
        key_file.write_text(random.Random(args.seed).randbytes(32).hex() + "\n")
        for signed in modes:
            root = Path(tmp) / f"robot-{int(signed)}"
            port = free_udp_port()
            with robot_ftp_process(root, f"udpin:127.0.0.1:{port}", key_file if signed else None):
                for i, (size, s, loss) in enumerate(cases):
                    if s != signed:
                        continue
                    rows.append(run_case(size, loss, signed, key_file if signed else None, port, root,
                                         args.seed * 1000 + i))
                    bar.update(1)
    return _table(rows, args.json, "UDP link emulator, 57600 baud 8N1 = 5760 B/s each way")


def _table(rows: list[dict], json_path: str | None, link: str) -> int:
    from ground_station.lab.bench.common import report

    table: list[tuple[str, object]] = [
        ("link", f"{link}, ground_station/mavlink/ftp_put.py: 239-byte writes, CRC-checked rounds"),
        ("theory", "WriteFile frames alone: t80 in 80-byte writes (the issue's yardstick), t239 in 239-byte (floor)")]
    for r in rows:
        name = f"{r['size'] // 1024:>4} KiB {'signed  ' if r['signed'] else 'unsigned'} loss {r['loss'] * 100:>4.0f}%"
        up, down = r.get("link_up", {}), r.get("link_down", {})
        seen = (f"lost up {up.get('lost', 0)}/{up.get('frames_in', 0)} down {down.get('lost', 0)}/"
                f"{down.get('frames_in', 0)}")
        if r["success"]:
            put = r.get("put", {})
            text = (f"{r['seconds']:7.2f} s  t80 {r['theoretical_s']:6.2f} s ratio {r['ratio']:.3f}  "
                    f"t239 {r['floor_s']:6.2f} s ratio {r['ratio_floor']:.3f}  puts {r['attempts']}  "
                    f"writes {put.get('writes_sent', '?')}/{put.get('blocks', '?')} blocks  {seen}  byte-exact")
        else:
            text = f"FAILED ({r.get('error', 'file differs on the robot')})"
        table.append((name, text))
    ok = all(r["success"] for r in rows)
    table.append(("all byte-exact", ok))
    report("upload", table, {"cases": rows, "all_success": ok}, json_path)
    return 0 if ok else 1
