"""The put engine (ground_station/mavlink/ftp_put.py) driven directly against
the robot's real FTP server core over an in-memory lossy FIFO link."""

import random

import pytest

from firmware_py.mavlink.ftp_server import FtpServer
from firmware_py.storage import Storage, ftp_crc32
from ground_station.mavlink.ftp_put import OP_TERMINATE, FtpPut, solve_gf2


def run(tmp_path, size, loss, seed, delay=0.05, step=0.005, drop=None):
    """`drop(request, reply)`: True loses that frame (reply None: the request) on top of `loss`."""
    storage = Storage(tmp_path / "root")
    srv = FtpServer(storage)
    data = random.Random(seed).randbytes(size)
    put = FtpPut(data, "/policies/p.qtab", session=0, seq=100)
    rng = random.Random(seed + 1)
    t, pending = 0.0, []
    while not put.finished and t < 300:
        for req in put.poll(t):
            if rng.random() < loss or drop is not None and drop(req, None):
                continue
            for rep in srv.handle(req + bytes(251 - len(req)), int(t * 1e6)):
                if rng.random() >= loss and not (drop is not None and drop(req, rep)):
                    pending.append((t + delay, rep))
        t += step
        while pending and pending[0][0] <= t:
            put.on_reply(pending.pop(0)[1], t)
    on_robot = (tmp_path / "root" / "policies" / "p.qtab").read_bytes()
    return put, data, on_robot


def test_lossless_put_is_one_round_one_frame_per_block(tmp_path):
    put, data, on_robot = run(tmp_path, 10240, 0.0, 1)
    assert put.state == "done" and on_robot == data
    assert put.stats.writes_sent == put.n_blocks == 43 and put.stats.rounds == 1
    assert put.opens == 2 and put.stats.reopened == 0  # CreateFile, the next round's open (sent ahead, unused)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_lossy_put_is_byte_exact_and_the_crc_tells_lost_acks_from_lost_writes(tmp_path, seed):
    put, data, on_robot = run(tmp_path, 30000, 0.2, seed)
    assert put.state == "done" and on_robot == data
    st = put.stats
    assert st.unknown > 0 and 0 < st.solved_lost < st.unknown  # some ACKs lost, some writes lost
    # a lost ACK no longer costs a copy: fewer frames than 1 / (1 - p)^2 = 1.5625 per block
    assert st.writes_sent / st.blocks < 1.45


def first_terminates(n_round, replies):
    """A drop hook losing the first two copies of round `n_round`'s TerminateSession
    (replies=False) or their two ACKs (replies=True)."""
    seqs: list[int] = []  # TerminateSession seqs, one per round
    copies: dict[int, int] = {}

    def drop(req, rep):
        if req[3] != OP_TERMINATE:  # header: seq (2 bytes), session, opcode
            return False
        seq = int.from_bytes(req[:2], "little")
        if rep is None:
            if seq not in seqs:
                seqs.append(seq)
            copies[seq] = copies.get(seq, 0) + 1
        ours = len(seqs) >= n_round and seq == seqs[n_round - 1] and copies[seq] <= 2
        return ours and (rep is not None) == replies
    return drop


@pytest.mark.parametrize("n_round", [1, 2])
@pytest.mark.parametrize("replies", [False, True])
def test_pipelined_open_is_redone_when_the_commit_or_its_ack_is_lost(tmp_path, n_round, replies):
    # the next round's OpenFileWO goes right behind the commit: when the commit's first
    # copies (or their ACKs) are lost, the open may have run before the commit (round 1:
    # on a file that does not exist yet), so the put opens again once a copy committed
    dropped = []

    def drop(req, rep):
        hit = base(req, rep)
        if hit:
            dropped.append(rep is not None)
        return hit
    base = first_terminates(n_round, replies)
    put, data, on_robot = run(tmp_path, 30000, 0.0, 5, drop=drop)
    assert dropped and all(d == replies for d in dropped)
    assert put.state == "done" and on_robot == data
    assert put.stats.reopened == 1


def test_nak_on_create_fails_with_the_code(tmp_path):
    storage = Storage(tmp_path / "root")
    srv = FtpServer(storage)
    put = FtpPut(b"x" * 10, "/policies/active.qtab", session=0, seq=0)  # protected
    for req in put.poll(0.0):
        for rep in srv.handle(req + bytes(251 - len(req)), 0):
            put.on_reply(rep, 0.01)
    assert put.state == "failed" and put.error.startswith("CreateFile NAK 9")


def test_no_reply_gives_up_after_a_bounded_number_of_copies():
    put = FtpPut(b"x" * 10, "/policies/a.qtab", session=0, seq=0)
    t, sent = 0.0, 0
    while not put.finished and t < 60:
        sent += len(put.poll(t))
        t += 0.05
    assert put.state == "failed" and "no reply to CreateFile" in put.error and sent <= 10


def test_solve_gf2_finds_the_unique_subset_and_refuses_ambiguity():
    rng = random.Random(4)
    vecs = [rng.getrandbits(32) for _ in range(16)]
    want = [1, 5, 9]
    target = vecs[1] ^ vecs[5] ^ vecs[9]
    assert solve_gf2(vecs, target) == want
    assert solve_gf2([3, 5, 6], 6) is None  # 3 ^ 5 == 6: two answers
    assert solve_gf2([1, 2], 4) is None  # no answer


def test_crc_is_linear_as_the_solver_assumes():
    rng = random.Random(5)
    a, b = rng.randbytes(500), rng.randbytes(500)
    assert ftp_crc32(bytes(x ^ y for x, y in zip(a, b, strict=True))) == ftp_crc32(a) ^ ftp_crc32(b)


def test_an_unlucky_round_is_cut_short_so_the_crc_can_still_sort_it_out(tmp_path):
    # at 35 % loss each way a round sized for ~20 unanswered writes often gets more than
    # the 28 the CRC can sort out; the round ends at 24 and the rest goes next round
    put, data, on_robot = run(tmp_path, 60000, 0.35, 1)
    assert put.state == "done" and on_robot == data
    assert put.stats.cut >= 1 and put.stats.unsolved == 0
