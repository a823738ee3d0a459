"""MAVLink over an emulated serial radio (ground_station/lab/rigs/serial_radio.py):
two pseudo-terminals joined at 57600 baud, SiK-like packet loss; then the
real programs over it: `qnav-robot --mavlink /dev/pts/N --mavlink-baud 57600`
and `qnav upload/mission/param/arm/mode/monitor --mavlink /dev/pts/M,57600`."""

from __future__ import annotations

import os
import select
import time

import pytest

from ground_station.canhub import CanHub
from ground_station.lab.rigs import hil_scenarios as hs
from ground_station.lab.rigs.serial_radio import RadioConfig, SerialRadio, split_frames

V2 = bytes([0xFD, 3, 0, 0, 7, 1, 1, 0, 0, 0]) + b"abc" + b"\x01\x02"  # unsigned, 3-byte payload
V2_SIGNED = bytes([0xFD, 1, 1, 0, 8, 1, 1, 0, 0, 0]) + b"z" + b"\x01\x02" + bytes(13)
V1 = bytes([0xFE, 2, 9, 1, 1, 0]) + b"hi" + b"\x03\x04"


def test_split_frames_finds_v1_v2_signed_frames_and_stray_bytes():
    buf = bytearray(b"\x00\x11" + V2 + V1 + V2_SIGNED + V2[:5])
    packets, used = split_frames(buf)
    assert packets == [b"\x00\x11", V2, V1, V2_SIGNED]
    assert used == len(buf) - 5  # the partial frame waits for its rest


def _read(fd: int, n: int, timeout_s: float) -> bytes:
    got = b""
    deadline = time.monotonic() + timeout_s
    while len(got) < n and time.monotonic() < deadline:
        if select.select([fd], [], [], 0.05)[0]:
            got += os.read(fd, 65536)
    return got


def _open(dev: str) -> int:
    import tty

    fd = os.open(dev, os.O_RDWR | os.O_NOCTTY)
    tty.setraw(fd)
    return fd


@pytest.mark.wallclock  # the transfer is timed on the wall clock: 0.70 s for 0.44 s once, in the parallel pass
def test_bytes_cross_at_the_baud_rate_both_ways_unchanged():
    frames = [bytes([0xFD, 200, 0, 0, i, 1, 1, 0, 0, 0]) + bytes([i]) * 200 + b"\xAA\xBB" for i in range(12)]
    data = b"".join(frames)  # 12 x 212 B = 2544 B: 0.44 s at 5760 B/s
    with SerialRadio(RadioConfig(baud=57600)) as radio:
        gcs, robot = _open(radio.gcs_device), _open(radio.robot_device)
        try:
            t0 = time.monotonic()
            os.write(gcs, data)
            got = _read(robot, len(data), 5)
            took = time.monotonic() - t0
            os.write(robot, V2)
            back = _read(gcs, len(V2), 2)
        finally:
            os.close(gcs)
            os.close(robot)
    assert got == data and back == V2
    assert radio.link_time(len(data)) * 0.95 <= took <= radio.link_time(len(data)) * 1.3, took
    assert radio.stats.up.frames_in == 12 and radio.stats.up.delivered == 12


def _through_radio(cfg: RadioConfig, data: bytes, want: int) -> tuple[bytes, SerialRadio]:
    """Write `data` into the ground end of a radio, read what reaches the robot end."""
    with SerialRadio(cfg) as radio:
        gcs, robot = _open(radio.gcs_device), _open(radio.robot_device)
        try:
            os.write(gcs, data)
            got = _read(robot, want, 1.5)
        finally:
            os.close(gcs)
            os.close(robot)
    return got, radio


def test_lost_packets_and_bytes_are_dropped_seeded():
    frames = [bytes([0xFD, 20, 0, 0, i, 1, 1, 0, 0, 0]) + bytes(20) + b"\x01\x02" for i in range(100)]
    got, radio = _through_radio(RadioConfig(baud=576000, loss=0.3, seed=5), b"".join(frames), 100 * 32)
    lost = radio.stats.up.lost
    assert 15 <= lost <= 45 and len(got) == (100 - lost) * 32
    got, radio = _through_radio(RadioConfig(baud=576000, byte_loss=0.1, seed=5), b"".join(frames), 100 * 32)
    assert radio.bytes_lost[0] > 100 and len(got) == 100 * 32 - radio.bytes_lost[0]


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_policy_upload_and_mission_a_b_over_the_57600_baud_radio(tmp_path):
    # two targets: every step of the operator's sequence and two MISSION_ITEM_REACHED cross the radio
    # (A,B,C,D over the same radio is the same code path for twice the sim time at x3 real time)
    policy = tmp_path / "paper10_cell.qtab"
    policy.write_bytes((hs.REPO / hs.CELL_POLICY).read_bytes())
    with SerialRadio(RadioConfig(baud=57600, seed=1)) as radio, CanHub("serialhil") as hub:
        r = hs.mission(hub.spec, tmp_path, robot_mavlink=radio.robot_device,
                       gcs_mavlink=f"{radio.gcs_device},57600", robot_extra=["--mavlink-baud", "57600"],
                       upload=policy, max_speed=3, targets="A,B")  # a real-time link (see hil_scenarios.mission)
    assert "error" not in r, r
    steps = {k: v["exit"] for k, v in r["steps"].items() if k != "monitor"}
    assert steps == {"upload": 0, "mission_upload": 0, "param_fs_off": 0, "arm": 0, "mode_auto": 0}, r["steps"]
    assert (tmp_path / "storage").is_dir()
    assert r["reached_seq"] == [0, 1], r.get("logs")
    assert r["robot"], r.get("logs")  # its --stats-json, written as it stops
    assert r["robot"]["transitions"][-1][3] == "mission complete"
    assert r["steps"]["monitor"]["lines"] >= 2  # `qnav monitor --plain` printed status lines over the radio
    assert radio.stats.down.bytes_in > 5000 and radio.stats.up.bytes_in > policy.stat().st_size
    # the robot read every byte the ground station sent; the other way, telemetry sent while no ground
    # station has the pty open (between two commands' processes) piles up in it and overflows it once
    # the gap is long enough, as with a radio left powered: how long depends on the machine's load
    assert radio.stats.up.overflowed == 0 and radio.stats.up.lost == 0 and radio.stats.down.lost == 0


def test_bench_upload_serial_is_byte_exact_and_reports_the_link_ratio(tmp_path):
    import contextlib
    import io
    import json

    from ground_station import cli

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        code = cli.main(["bench", "upload", "--serial", "--sizes", "3000", "--losses", "0,0.05",
                         "--signing", "off", "--json", str(tmp_path / "b.json")])
    assert code == 0, out.getvalue()
    cases = json.loads((tmp_path / "b.json").read_text())["cases"]
    assert [(c["link"], c["loss"], c["byte_exact"]) for c in cases] == [("serial", 0.0, True), ("serial", 0.05, True)]
    # the radio does throttle: no put beats the file sent as 239-byte writes at the baud rate (t239,
    # the floor); t80 (80-byte writes, the older yardstick) the put engine does beat
    assert cases[0]["seconds"] >= cases[0]["floor_s"] * 0.95
    assert "emulated serial radio" in out.getvalue()
