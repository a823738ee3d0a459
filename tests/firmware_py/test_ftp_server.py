"""FtpServer driven directly: the MAVLink FTP state machine without sockets."""

import os
import struct
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_py.mavlink.ftp_server import HEADER, MAX_DATA, PAYLOAD_LEN, FtpServer, Nak, Op, parse
from firmware_py.storage import ACTIVE_POLICY, LAST_GOOD_POLICY, Storage
from tests.support.background import pending

S = 1_000_000  # µs per second


def req(seq, opcode, data=b"", session=0, offset=0, size=None):
    size = len(data) if size is None else size
    p = HEADER.pack(seq, session, opcode, size, 0, 0, 0, offset) + data
    return p + bytes(PAYLOAD_LEN - len(p)) if len(p) < PAYLOAD_LEN else p


class Client:
    """Just enough of a client to drive the server in tests."""

    def __init__(self, server, session=0, owner=(255, 190)):
        self.server, self.session, self.seq, self.now = server, session, 0, 0
        self.owner = owner

    def send(self, opcode, data=b"", offset=0, size=None, session=None):
        self.seq += 1
        payload = req(self.seq, opcode, data, self.session if session is None else session, offset, size)
        self.last = payload
        return [parse(r) for r in self.server.handle(payload, self.now, self.owner)]

    def one(self, *a, **k):
        replies = self.send(*a, **k)
        assert len(replies) == 1
        return replies[0]


def ack(reply):
    return reply[2] == Op.ACK


def nak(reply, code):
    return reply[2] == Op.NAK and reply[7][:1] == bytes([code])


@pytest.fixture
def server(tmp_path):
    return FtpServer(Storage(tmp_path / "root", quota_bytes=200_000))


@pytest.fixture
def c(server):
    return Client(server)


def put(c, path, data, block=80):
    assert ack(c.one(Op.CREATE_FILE, path.encode()))
    for off in range(0, len(data), block):
        assert ack(c.one(Op.WRITE_FILE, data[off:off + block], offset=off))
    assert ack(c.one(Op.TERMINATE_SESSION))


def test_reply_header_echoes_request(c):
    c.seq = 41
    r = c.one(Op.CREATE_FILE, b"/policies/a", offset=7, session=9)
    seq, session, opcode, size, req_opcode, burst, offset, data = r
    assert (seq, session, opcode, size, req_opcode, burst, offset) == (43, 9, Op.ACK, 0, Op.CREATE_FILE, 0, 7)


def test_seq_wraps(c):
    c.seq = 65534
    r = c.one(Op.RESET_SESSIONS)
    assert r[0] == 0 and ack(r)


def test_upload_is_invisible_until_terminate(server, c):
    data = os.urandom(1000)
    assert ack(c.one(Op.CREATE_FILE, b"/policies/p.qtab"))
    for off in range(0, 1000, 239):
        assert ack(c.one(Op.WRITE_FILE, data[off:off + 239], offset=off))
    root = server.storage.root / "policies"
    assert not (root / "p.qtab").exists()
    listing = c.one(Op.LIST_DIRECTORY, b"/policies", session=50)
    assert nak(listing, Nak.EOF)  # the temporary file is not listed
    assert ack(c.one(Op.TERMINATE_SESSION))
    assert (root / "p.qtab").read_bytes() == data
    assert os.listdir(root) == ["p.qtab"]
    assert server.stats.commits == 1


def test_read_back_with_read_and_burst(server, c):
    data = os.urandom(5000)
    put(c, "/policies/r.bin", data)
    r = c.one(Op.OPEN_FILE_RO, b"/policies/r.bin", session=3)
    assert ack(r) and struct.unpack("<I", r[7])[0] == 5000
    got = bytearray()
    replies = c.send(Op.BURST_READ_FILE, size=80, offset=0, session=3)
    first_seq = c.seq + 1
    assert [p[0] for p in replies] == list(range(first_seq, first_seq + len(replies)))
    assert replies[-1][5] == 1 and all(p[5] == 0 for p in replies[:-1])
    for p in replies:
        assert p[6] == len(got)
        got += p[7]
    while len(got) < 5000:  # continue bursts as pymavlink does
        replies = c.send(Op.BURST_READ_FILE, size=80, offset=len(got), session=3)
        for p in replies:
            got += p[7]
    assert bytes(got) == data
    assert nak(c.one(Op.BURST_READ_FILE, size=80, offset=5000, session=3), Nak.EOF)
    r = c.one(Op.READ_FILE, size=239, offset=4900, session=3)
    assert ack(r) and r[7] == data[4900:] and r[6] == 4900
    assert nak(c.one(Op.READ_FILE, size=239, offset=5000, session=3), Nak.EOF)
    assert nak(c.one(Op.READ_FILE, size=239, offset=2**32 - 1, session=3), Nak.EOF)
    assert ack(c.one(Op.TERMINATE_SESSION, session=3))
    assert nak(c.one(Op.READ_FILE, size=10, session=3), Nak.INVALID_SESSION)


def test_calc_crc32_uses_the_ftp_crc(c):
    put(c, "/params/n.txt", b"123456789")
    r = c.one(Op.CALC_FILE_CRC32, b"/params/n.txt")
    assert ack(r) and struct.unpack("<I", r[7])[0] == 0x2DFD2D88
    assert nak(c.one(Op.CALC_FILE_CRC32, b"/params/missing"), Nak.FILE_NOT_FOUND)


@pytest.mark.parametrize("opcode", [Op.LIST_DIRECTORY, Op.LIST_DIRECTORY_WITH_TIME])
def test_list_directory_pages_by_entry_offset(c, opcode):
    names = [f"file_{i:03d}_with_a_long_name.qtab" for i in range(30)]
    for n in names:
        put(c, f"/policies/{n}", n.encode())
    c.one(Op.CREATE_DIRECTORY, b"/policies/sub")
    entries = []
    while True:
        r = c.one(opcode, b"/policies", offset=len(entries))
        if nak(r, Nak.EOF):
            break
        assert ack(r) and len(r[7]) <= MAX_DATA
        entries += [e.decode() for e in r[7].split(b"\0") if e]
    assert len(entries) == 31
    files = [e for e in entries if e[0] == "F"]
    fields = files[0][1:].split("\t")
    assert fields[0] == names[0] and fields[1] == str(len(names[0]))
    assert len(fields) == (3 if opcode == Op.LIST_DIRECTORY_WITH_TIME else 2)
    assert [e for e in entries if e[0] == "D"][0].split("\t")[0] == "Dsub"
    assert nak(c.one(opcode, b"/nope"), Nak.FILE_NOT_FOUND)


def test_file_and_directory_operations(server, c):
    put(c, "/policies/a", b"0123456789")
    assert ack(c.one(Op.TRUNCATE_FILE, b"/policies/a", offset=3))
    assert server.storage.read_bytes("/policies/a") == b"012"
    assert ack(c.one(Op.OPEN_FILE_WO, b"/policies/a", session=4))
    assert ack(c.one(Op.WRITE_FILE, b"XY", offset=2, session=4))
    assert server.storage.read_bytes("/policies/a") == b"012"  # not until terminate
    assert ack(c.one(Op.TERMINATE_SESSION, session=4))
    assert server.storage.read_bytes("/policies/a") == b"01XY"
    assert ack(c.one(Op.CREATE_DIRECTORY, b"/policies/d"))
    assert nak(c.one(Op.CREATE_DIRECTORY, b"/policies/d"), Nak.FILE_EXISTS)
    assert ack(c.one(Op.RENAME, b"/policies/a\0/policies/d/b"))
    assert nak(c.one(Op.REMOVE_DIRECTORY, b"/policies/d"), Nak.FAIL_ERRNO)
    assert nak(c.one(Op.REMOVE_FILE, b"/policies/a"), Nak.FILE_NOT_FOUND)
    assert ack(c.one(Op.REMOVE_FILE, b"/policies/d/b"))
    assert ack(c.one(Op.REMOVE_DIRECTORY, b"/policies/d"))
    assert os.listdir(server.storage.root / "policies") == []


def test_retried_request_gets_the_cached_reply_not_a_second_run(server, c):
    put(c, "/policies/a", b"abc")
    first = c.one(Op.RENAME, b"/policies/a\0/policies/b")
    assert ack(first)
    again = [parse(r) for r in server.handle(c.last, c.now, c.owner)]  # same seq: the ACK was lost
    assert again == [first]
    assert server.stats.retries_answered_from_cache == 1
    fresh = c.one(Op.RENAME, b"/policies/a\0/policies/b")  # new seq: really runs, and fails
    assert nak(fresh, Nak.FILE_NOT_FOUND)


def test_create_retry_keeps_written_data(server, c):
    assert ack(c.one(Op.CREATE_FILE, b"/policies/a"))
    create = c.last
    assert ack(c.one(Op.WRITE_FILE, b"data", offset=0))
    assert ack(parse(server.handle(create, c.now, c.owner)[0]))  # not the last request: runs again
    # re-running CreateFile on the same session starts the file over, as the client asked
    assert ack(c.one(Op.TERMINATE_SESSION))
    assert server.storage.read_bytes("/policies/a") == b""


@pytest.mark.parametrize("opcode", [0, 17, 100, 127, 200, 255])
def test_unknown_opcodes_are_nakked(c, opcode):
    assert nak(c.one(opcode), Nak.UNKNOWN_COMMAND)


def test_hostile_payloads(server, c):
    assert server.handle(b"\x01\x02\x03", 0) == []  # no header: nothing to answer
    assert nak(c.one(Op.WRITE_FILE, b"x", size=240), Nak.INVALID_DATA_SIZE)
    short = HEADER.pack(1, 0, Op.CREATE_FILE, 100, 0, 0, 0, 0) + b"/policies/a"
    assert nak(parse(server.handle(short, 0)[0]), Nak.INVALID_DATA_SIZE)
    assert nak(c.one(Op.WRITE_FILE, b"x", session=77), Nak.INVALID_SESSION)
    assert nak(c.one(Op.TERMINATE_SESSION, session=78), Nak.INVALID_SESSION)
    assert nak(c.one(Op.CREATE_FILE, b"\xff\xfe"), Nak.FAIL)
    assert nak(c.one(Op.RENAME, b"/policies/only_one_name"), Nak.FAIL)
    assert ack(c.one(Op.CREATE_FILE, b"/policies/big"))
    huge = c.one(Op.WRITE_FILE, b"x", offset=0xFFFFFFF0)  # a sparse write far past the end: a hole
    assert huge[2] == Op.NAK and huge[7][:1] == bytes([Nak.FAIL_ERRNO]) and huge[7][1] == 22  # EINVAL
    assert nak(c.one(Op.OPEN_FILE_RO, b"/policies"), Nak.FAIL_ERRNO)  # a directory
    assert server.handle(HEADER.pack(1, 0, Op.ACK, 0, 0, 0, 0, 0), 0) == []  # replies are ignored


def test_path_escapes_are_refused_and_nothing_is_written_outside(tmp_path, server, c):
    outside = tmp_path / "outside"
    outside.mkdir()
    os.symlink(outside, server.storage.root / "policies" / "link")
    (outside / "secret").write_bytes(b"s")
    before = sorted(p.name for p in tmp_path.iterdir())
    for path in (b"../x", b"/../../x", b"/policies/../../x", b"/policies/link/x", b"policies/link/x"):
        assert nak(c.one(Op.CREATE_FILE, path), Nak.FILE_PROTECTED), path
        assert nak(c.one(Op.CREATE_DIRECTORY, path), Nak.FILE_PROTECTED), path
    assert nak(c.one(Op.OPEN_FILE_RO, b"/policies/link/secret"), Nak.FILE_PROTECTED)
    assert nak(c.one(Op.OPEN_FILE_RO, b"/etc/passwd"), Nak.FILE_NOT_FOUND)  # / is the storage root
    assert nak(c.one(Op.CREATE_FILE, b"/etc/passwd"), Nak.FILE_NOT_FOUND)
    assert nak(c.one(Op.REMOVE_FILE, b"/policies/link/secret"), Nak.FILE_PROTECTED)
    put(c, "/policies/ok", b"fine")
    assert nak(c.one(Op.RENAME, b"/policies/ok\0../stolen"), Nak.FILE_PROTECTED)
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert sorted(p.name for p in outside.iterdir()) == ["secret"]
    assert not (server.storage.root / "etc").exists()


def test_idle_sessions_expire_on_the_injected_clock(server, c):
    assert ack(c.one(Op.CREATE_FILE, b"/policies/slow"))
    assert ack(c.one(Op.WRITE_FILE, b"part", offset=0))
    c.now = 4 * S
    assert ack(c.one(Op.WRITE_FILE, b"more", offset=4))  # activity keeps it alive
    c.now = 10 * S
    assert nak(c.one(Op.WRITE_FILE, b"late", offset=8), Nak.INVALID_SESSION)
    assert server.stats.expired_sessions == 1
    assert os.listdir(server.storage.root / "policies") == []  # temp removed, nothing committed


def test_reset_sessions_discards_uploads_and_sessions_are_limited(server, c):
    other = Client(server, owner=(7, 1))
    for sid in range(2):  # per client: max_sessions_per_client
        assert ack(c.one(Op.CREATE_FILE, f"/policies/f{sid}".encode(), session=sid))
        assert ack(other.one(Op.CREATE_FILE, f"/policies/g{sid}".encode(), session=sid))
    assert nak(c.one(Op.CREATE_FILE, b"/policies/f9", session=9), Nak.NO_SESSIONS_AVAILABLE)
    third = Client(server, owner=(8, 1))  # the table is full and nobody is idle yet
    assert nak(third.one(Op.CREATE_FILE, b"/policies/h0"), Nak.NO_SESSIONS_AVAILABLE)
    assert ack(c.one(Op.RESET_SESSIONS))  # resets the caller's sessions only
    assert sorted(server.sessions) == [((7, 1), 0), ((7, 1), 1)]
    assert ack(other.one(Op.RESET_SESSIONS))
    assert server.sessions == {}
    assert os.listdir(server.storage.root / "policies") == []


def test_rename_onto_active_activates_through_the_hook(tmp_path):
    seen = []

    def activate(path):
        seen.append(Path(path).read_bytes())
        if seen[-1].startswith(b"BAD"):
            return False, "CRC mismatch in table"
        return True, "id 0x1"

    server = FtpServer(Storage(tmp_path / "root"), activate=activate)
    c = Client(server)
    put(c, "/policies/one.qtab", b"GOOD one")
    assert ack(c.one(Op.RENAME, b"/policies/one.qtab\0/policies/active.qtab"))
    put(c, "/policies/two.qtab", b"GOOD two")
    assert ack(c.one(Op.RENAME, b"/policies/two.qtab\0/policies/./active.qtab"))
    store = server.storage
    assert store.read_bytes(ACTIVE_POLICY) == b"GOOD two"
    assert store.read_bytes(LAST_GOOD_POLICY) == b"GOOD one"
    assert [t for _s, t in server.drain_texts()] == ["policy active: id 0x1"] * 2
    put(c, "/policies/bad.qtab", b"BAD table")
    assert nak(c.one(Op.RENAME, b"/policies/bad.qtab\0/policies/active.qtab"), Nak.FAIL)
    assert server.drain_texts() == [(4, "policy refused: CRC mismatch in table")]
    assert store.read_bytes(ACTIVE_POLICY) == b"GOOD two"
    assert store.read_bytes(LAST_GOOD_POLICY) == b"GOOD one"
    assert store.read_bytes("/policies/bad.qtab") == b"BAD table"
    # the slots can only change through activation
    for op, data in ((Op.CREATE_FILE, b"/policies/active.qtab"), (Op.OPEN_FILE_WO, b"/policies/last_good.qtab"),
                     (Op.REMOVE_FILE, b"/policies/active.qtab"), (Op.TRUNCATE_FILE, b"/policies/active.qtab"),
                     (Op.RENAME, b"/policies/active.qtab\0/policies/x"),
                     (Op.RENAME, b"/policies/bad.qtab\0/policies/last_good.qtab")):
        assert nak(c.one(op, data), Nak.FILE_PROTECTED), (op, data)
    assert store.read_bytes(ACTIVE_POLICY) == b"GOOD two"
    # the robot's own folders: nothing new can be made in them either (issue 43)
    for op, data in ((Op.CREATE_FILE, b"/metadata/x.json"), (Op.CREATE_DIRECTORY, b"/metadata/sub"),
                     (Op.CREATE_FILE, b"/logs/robot.log"), (Op.RENAME, b"/policies/bad.qtab\0/metadata/y")):
        assert nak(c.one(op, data), Nak.FILE_PROTECTED), (op, data)


def test_hook_that_raises_is_a_refusal(tmp_path):
    def activate(path):
        raise RuntimeError("vehicle busy")

    server = FtpServer(Storage(tmp_path / "root"), activate=activate)
    c = Client(server)
    put(c, "/policies/x.qtab", b"x")
    assert nak(c.one(Op.RENAME, b"/policies/x.qtab\0/policies/active.qtab"), Nak.FAIL)
    assert "vehicle busy" in server.drain_texts()[0][1]
    no_hook = FtpServer(Storage(tmp_path / "root2"))
    c2 = Client(no_hook)
    put(c2, "/policies/x.qtab", b"x")
    assert nak(c2.one(Op.RENAME, b"/policies/x.qtab\0/policies/active.qtab"), Nak.FAIL)


@settings(max_examples=400, deadline=None)
@given(st.binary(min_size=0, max_size=260), st.integers(0, 60 * S))
def test_random_payloads_never_raise_and_replies_are_well_formed(tmp_path_factory, payload, now):
    server = FtpServer(Storage(tmp_path_factory.mktemp("fuzz"), quota_bytes=50_000))
    replies = server.handle(payload, now)
    for r in replies:
        assert HEADER.size <= len(r) <= PAYLOAD_LEN
        seq, _s, opcode, size, req_opcode, _b, _o, data = parse(r)
        assert opcode in (Op.ACK, Op.NAK) and size == len(data)
        assert req_opcode == payload[3] and seq == (int.from_bytes(payload[:2], "little") + 1) % 65536 or \
            req_opcode == Op.BURST_READ_FILE
    server.close()


def test_whole_file_work_is_answered_from_the_offload_worker_and_a_retry_starts_nothing(tmp_path, monkeypatch):
    """Issue 29 finding 8: CalcFileCRC32 (reads the whole file) and TerminateSession's commit (fsyncs)
    run on the offload worker; the link thread gets no reply until `poll` has it."""
    from firmware_py.background import Background

    work = Background(threaded=False)  # stepped here, so the test sees the moment in between
    server = FtpServer(Storage(tmp_path / "root", quota_bytes=200_000), offload=work)
    c = Client(server)
    data = bytes(range(256)) * 300
    assert ack(c.one(Op.CREATE_FILE, b"/policies/big.bin"))
    assert ack(c.one(Op.WRITE_FILE, data[:200]))
    assert c.send(Op.TERMINATE_SESSION) == [] and server.poll(c.now) == []  # committed off the link thread
    assert not (tmp_path / "root" / "policies" / "big.bin").exists() and work.run_pending() == 1
    (owner, reply), = server.poll(c.now)
    assert owner == c.owner and ack(parse(reply)) and parse(reply)[0] == c.seq + 1
    assert (tmp_path / "root" / "policies" / "big.bin").read_bytes() == data[:200]
    (small,) = c.send(Op.CALC_FILE_CRC32, b"/policies/big.bin")  # 200 B: summed at once (INLINE_CRC_BYTES)
    assert ack(small) and pending(work) == 0
    monkeypatch.setattr("firmware_py.mavlink.ftp_server.INLINE_CRC_BYTES", 100)  # as if it were large
    assert c.send(Op.CALC_FILE_CRC32, b"/policies/big.bin") == []
    again = server.handle(c.last, c.now, c.owner)  # the same request again (a lost reply's retry)
    assert again == [] and pending(work) == 1  # no second job
    work.run_pending()
    (_, reply), = server.poll(c.now)
    crc = server.storage.crc32("/policies/big.bin")  # the same sum the link thread computed before
    assert ack(parse(reply)) and struct.unpack("<I", parse(reply)[7][:4])[0] == crc
    assert [parse(r) for r in server.handle(c.last, c.now, c.owner)] == [parse(reply)]  # now from the cache
    (gone,) = c.send(Op.CALC_FILE_CRC32, b"/policies/none.bin")
    assert nak(gone, Nak.FILE_NOT_FOUND)  # no such file: said at once
    c.seq += 5  # a new request, not a retry
    assert c.send(Op.CALC_FILE_CRC32, b"/policies/big.bin") == []
    (tmp_path / "root" / "policies" / "big.bin").unlink()  # removed before the worker reads it
    assert work.run_pending() == 1
    (_, reply), = server.poll(c.now)
    assert nak(parse(reply), Nak.FILE_NOT_FOUND)  # the worker's OSError is a NAK, never raised
