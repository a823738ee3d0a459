"""ground_station/lab/rigs/link_emulator.py: the scheduling rules (pure) and the relay over UDP."""

import socket
import subprocess
import sys

import pytest

from ground_station.lab.rigs import link_emulator as emu


def scheduled(link):
    """(arrival, direction, data) in delivery order, without running the thread."""
    return [(t, d, data) for t, _n, d, data in sorted(link._heap)]


@pytest.fixture
def make_link():
    links = []

    def make(**cfg):
        link = emu.LinkEmulator(emu.LinkConfig(**cfg))
        links.append(link)
        return link

    yield make
    for link in links:
        link.stop()


def test_frames_queue_at_the_byte_rate_then_add_latency(make_link):
    link = make_link(baud=57600, latency_s=0.1)
    for i in range(5):
        link._schedule(emu.UP, bytes([i]) * 576, now=10.0)  # 576 B = 0.1 s at 5760 B/s
    arrivals = [t for t, _d, _x in scheduled(link)]
    assert arrivals == pytest.approx([10.0 + 0.1 * (k + 1) + 0.1 for k in range(5)])
    link._schedule(emu.DOWN, b"x" * 576, now=10.0)  # the other direction has its own air
    down = [t for t, d, _x in scheduled(link) if d == emu.DOWN]
    assert down == [pytest.approx(10.2)]
    assert link.config.bytes_per_s == 5760


def test_loss_is_seeded_and_near_the_requested_rate(make_link):
    def lost_frames(seed):
        link = make_link(loss=0.2, seed=seed)
        for i in range(2000):
            link._schedule(emu.UP, i.to_bytes(2, "little"), now=0.0)
        kept = {data for _t, _d, data in scheduled(link)}
        return {i for i in range(2000) if i.to_bytes(2, "little") not in kept}, link

    a, link = lost_frames(7)
    b, _ = lost_frames(7)
    c, _ = lost_frames(8)
    assert a == b and a != c
    assert 300 < len(a) < 500 and link.stats.up.lost == len(a)
    # a lost frame still used its air time: the next frame waits for it
    assert link._free_at[emu.UP] == pytest.approx(2000 * 2 / link.config.bytes_per_s)


def test_duplicates_and_reordering(make_link):
    link = make_link(duplicate=1.0)
    link._schedule(emu.UP, b"a" * 100, now=0.0)
    assert [d for _t, _dir, d in scheduled(link)] == [b"a" * 100] * 2
    link = make_link(reorder=0.5, reorder_delay_s=1.0, seed=3)
    frames = [bytes([i]) * 10 for i in range(40)]
    for f in frames:
        link._schedule(emu.UP, f, now=0.0)
    order = [d for _t, _dir, d in scheduled(link)]
    assert sorted(order) == sorted(frames) and order != frames
    assert 0 < link.stats.up.reordered < 40


def test_queue_limit_drops_overflow(make_link):
    link = make_link(queue_bytes=1000)
    for _ in range(20):
        link._schedule(emu.UP, b"x" * 100, now=0.0)
    assert len(link._heap) == 10 and link.stats.up.overflowed == 10


def test_bad_config_is_refused():
    with pytest.raises(ValueError, match="loss"):
        emu.LinkEmulator(emu.LinkConfig(loss=1.5))


def _udp(port=0):
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", port))
    s.settimeout(2.0)
    return s


def test_relays_both_ways_over_udp_with_learnt_and_fixed_peers():
    robot = _udp()
    gcs = _udp()
    try:
        cfg = emu.LinkConfig(baud=10_000_000, duplicate=0.0)
        with emu.LinkEmulator(cfg, robot_peer=robot.getsockname()) as link:
            frames = [bytes([i]) * (20 + i) for i in range(30)]
            for f in frames:
                gcs.sendto(f, ("127.0.0.1", link.gcs_port))
            got = [robot.recvfrom(1000) for _ in frames]
            assert [d for d, _a in got] == frames
            assert got[0][1] == ("127.0.0.1", link.robot_port)
            robot.sendto(b"reply", ("127.0.0.1", link.robot_port))
            data, addr = gcs.recvfrom(1000)  # the gcs address was learnt from its frames
            assert data == b"reply" and addr == ("127.0.0.1", link.gcs_port)
            assert link.stats.up.delivered == 30 and link.stats.down.delivered == 1
    finally:
        robot.close()
        gcs.close()


def test_duplicating_link_over_udp():
    robot = _udp()
    gcs = _udp()
    try:
        with emu.LinkEmulator(emu.LinkConfig(baud=10_000_000, duplicate=1.0),
                              robot_peer=robot.getsockname()) as link:
            gcs.sendto(b"once", ("127.0.0.1", link.gcs_port))
            assert robot.recvfrom(100)[0] == b"once"
            assert robot.recvfrom(100)[0] == b"once"
    finally:
        robot.close()
        gcs.close()


def test_cli_help():
    out = subprocess.run([sys.executable, "-m", "ground_station.lab.rigs.link_emulator", "--help"],
                         capture_output=True, text=True, timeout=30)
    assert out.returncode == 0 and "--loss" in out.stdout and "--seed" in out.stdout
