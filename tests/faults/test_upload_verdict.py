"""`qnav upload`'s verdict when exactly the frames that decide it are lost.

A real `qnav-robot` behind the link emulator (no random loss) whose `drop`
predicate loses chosen frames: Rename requests or replies, PARAM_VALUEs,
CreateFile requests. The new policy has the size of the one the robot runs,
so both have the same whole-file CRC32 (each .qtab ends in its own CRC32):
the CRC alone cannot tell them apart, only the robot's POLICY_* parameters
can. Every verdict is checked against the robot's disk."""

import random

import pytest

from firmware_py.policy import load_policy
from firmware_py.storage import ACTIVE_POLICY, Storage, ftp_crc32
from ground_station.lab.faults.common import RobotProcess
from ground_station.lab.faults.crash import policy_version
from ground_station.lab.rigs import link_emulator
from ground_station.lab.rigs.lockstep import CELL_POLICY
from ground_station.mavlink.ftp_upload import upload_policy
from ground_station.mavlink.link import Link, LinkError

UP, DOWN = 0, 1
MSG_PARAM_VALUE, MSG_FTP = 22, 110
OP_CREATE_FILE, OP_RENAME = 6, 13


def _frame(data: bytes) -> tuple[int, bytes]:
    """(msgid, payload with MAVLink 2's trimmed zeros restored) of one frame."""
    if len(data) < 12 or data[0] != 0xFD:
        return -1, b""
    return int.from_bytes(data[7:10], "little"), data[10:10 + data[1]] + bytes(260)


def ftp_request(opcode: int):
    return lambda d, data: d == UP and _frame(data)[0] == MSG_FTP and _frame(data)[1][3 + 3] == opcode


def ftp_reply_to(opcode: int):
    return lambda d, data: d == DOWN and _frame(data)[0] == MSG_FTP and _frame(data)[1][3 + 5] == opcode


def param_value(d: int, data: bytes) -> bool:
    return d == DOWN and _frame(data)[0] == MSG_PARAM_VALUE


class Dropper:
    """Drop the first `n` frames each rule matches (n None: all of them)."""

    def __init__(self, *rules) -> None:
        self.rules = [[match, n, 0] for match, n in rules]

    def __call__(self, direction: int, data: bytes) -> bool:
        for rule in self.rules:
            match, n, done = rule
            if (n is None or done < n) and match(direction, data):
                rule[2] += 1
                return True
        return False

    def count(self, i: int) -> int:
        return self.rules[i][2]


@pytest.fixture
def rig(tmp_path):
    """(start(dropper) -> connected Link, storage, base bytes, new policy path); everything stopped after."""
    emu = link_emulator
    storage_dir = tmp_path / "robot"
    base = CELL_POLICY.read_bytes()
    Storage(storage_dir).write_atomic(ACTIVE_POLICY, base)
    new = policy_version(CELL_POLICY, 0x7E570000 + random.Random(1).randrange(0xFFFF))
    assert len(new) == len(base) and ftp_crc32(new) == ftp_crc32(base)  # the CRC cannot tell them apart
    local = tmp_path / "new.qtab"
    local.write_bytes(new)
    started = []

    def start(dropper):
        robot = RobotProcess(storage_dir, log=tmp_path / "robot.log").start()
        started.append(robot)
        link = emu.LinkEmulator(emu.LinkConfig(seed=1), robot_peer=("127.0.0.1", robot.port), drop=dropper)
        started.append(link.start())
        gcs = Link(f"udpout:127.0.0.1:{link.gcs_port}", tlog=False)
        started.append(gcs)
        gcs.connect(30.0)
        return gcs

    yield start, Storage(storage_dir), base, local
    for thing in reversed(started):
        (thing.close if isinstance(thing, Link) else thing.stop)()


def active_bytes(storage) -> bytes:
    return storage.resolve(ACTIVE_POLICY).read_bytes()


def test_rename_never_arrives_and_params_lost_is_a_timeout_not_a_success(rig):
    # the false success found under 40 % loss: rename lost, POLICY_ID read lost, and the
    # CRC of active.qtab (same for both versions) taken as proof
    start, storage, base, local = rig
    drop = Dropper((ftp_request(OP_RENAME), None), (param_value, None))
    gcs = start(drop)
    with pytest.raises(LinkError) as exc:
        upload_policy(gcs, local, "/policies/new.qtab", activate=True, deadline_s=8.0)
    assert exc.value.code == 4 and "\n" not in str(exc.value) and "not confirmed" in str(exc.value)
    assert drop.count(0) >= 1
    assert active_bytes(storage) == base
    assert storage.resolve("/policies/new.qtab").read_bytes() == local.read_bytes()  # uploaded, not active


def test_lost_renames_and_lost_reads_are_retried_until_the_robot_reports_the_new_policy(rig):
    start, storage, base, local = rig
    drop = Dropper((ftp_request(OP_RENAME), 2), (param_value, 5))
    gcs = start(drop)
    res = upload_policy(gcs, local, "/policies/new.qtab", activate=True, deadline_s=60.0)
    assert res.activated and res.renames == 3 and drop.count(0) == 2 and drop.count(1) == 5
    assert "POLICY_ID" in res.confirmed_by
    assert active_bytes(storage) == local.read_bytes()
    got = gcs.read_params(("POLICY_CRC_HI", "POLICY_CRC_LO"), budget_s=5.0)
    crc = load_policy(local.read_bytes()).crc
    assert (got["POLICY_CRC_HI"], got["POLICY_CRC_LO"]) == (crc >> 16, crc & 0xFFFF)


def test_lost_rename_reply_is_resolved_by_the_robot_state_without_a_second_rename(rig):
    # the false failure: the robot activated, one reply/read was lost
    start, storage, base, local = rig
    drop = Dropper((ftp_reply_to(OP_RENAME), None), (param_value, 4))
    gcs = start(drop)
    res = upload_policy(gcs, local, "/policies/new.qtab", activate=True, deadline_s=60.0)
    assert res.activated and res.renames == 1 and drop.count(0) == 1
    assert active_bytes(storage) == local.read_bytes()


def test_a_stale_same_size_file_under_the_remote_name_never_passes_for_the_upload(rig):
    # a different valid policy already at the remote name has the same CRC32; with every
    # CreateFile lost nothing new arrives, and the upload must not be "verified"
    start, storage, base, local = rig
    storage.write_atomic("/policies/new.qtab", base)
    drop = Dropper((ftp_request(OP_CREATE_FILE), None))
    gcs = start(drop)
    with pytest.raises(LinkError) as exc:
        upload_policy(gcs, local, "/policies/new.qtab", deadline_s=20.0, attempts=2)
    assert exc.value.code in (4, 5) and "not verified" in str(exc.value)
    assert drop.count(0) >= 2  # both puts sent CreateFile (copies included), all lost
    assert active_bytes(storage) == base
