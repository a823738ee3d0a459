"""FTP activation against the real controller: FtpServer's Rename onto
active.qtab calls Controller.activate_policy; refusals leave the old policy
driving; boot picks the newest valid file."""

from ctrl_support import Kinematic, Rig, sector_seek_policy

from firmware_py.control.controller import Controller
from firmware_py.mavlink.ftp_server import HEADER, PAYLOAD_LEN, FtpServer, Nak, Op, parse
from firmware_py.policy import PolicyError, dump_policy, load_policy
from firmware_py.storage import ACTIVE_POLICY, LAST_GOOD_POLICY, Storage, boot_policy_candidates
from firmware_py.vehicle import CtrlState, Mode, VehicleConfig


class FtpClient:
    def __init__(self, server):
        self.server, self.seq = server, 0

    def send(self, opcode, data=b"", offset=0):
        self.seq += 1
        p = HEADER.pack(self.seq, 0, opcode, len(data), 0, 0, 0, offset) + data
        return parse(self.server.handle(p.ljust(PAYLOAD_LEN, b"\0"), 0)[0])

    def put(self, path, data):
        assert self.send(Op.CREATE_FILE, path.encode())[2] == Op.ACK
        for off in range(0, len(data), 200):
            assert self.send(Op.WRITE_FILE, data[off:off + 200], off)[2] == Op.ACK
        assert self.send(Op.TERMINATE_SESSION)[2] == Op.ACK

    def activate(self, path):
        return self.send(Op.RENAME, path.encode() + b"\0" + ACTIVE_POLICY.encode())


def policy_bytes(policy_id, scale=0.5):
    base = sector_seek_policy(policy_id=1)
    return dump_policy(base.encoder, base.table.tolist(), "int8", scale, policy_id=policy_id,
                       map_geometry=base.map_geometry)


def test_refused_while_driving_and_when_corrupt_then_activated_with_last_good(tmp_path):
    ctrl = Controller(VehicleConfig(), load_policy(policy_bytes(11)), start_pose_mm=(0, 0, 0))
    rig = Rig(ctrl, Kinematic(0, 0, 0))
    rig.tick()
    assert ctrl.arm() == (True, "")
    store = Storage(tmp_path / "root")
    store.write_atomic(ACTIVE_POLICY, policy_bytes(11))
    server = FtpServer(store, activate=ctrl.activate_policy)
    c = FtpClient(server)

    c.put("/policies/new.qtab", policy_bytes(22))
    assert ctrl.set_goal(5000, 0) == (True, "")
    rig.tick()
    assert ctrl.state == CtrlState.DRIVING
    r = c.activate("/policies/new.qtab")
    assert r[2] == Op.NAK and r[7] == bytes([Nak.FAIL])
    assert server.drain_texts() == [(4, "policy refused: refused while driving: stop first")]
    moving = len([m for m in rig.commands if m is not None])
    for _ in range(5):
        rig.tick()
    assert ctrl.policy.policy_id == 11 and ctrl.state == CtrlState.DRIVING
    assert len([m for m in rig.commands if m is not None]) == moving + 5  # the old policy keeps driving
    assert load_policy(store.resolve(ACTIVE_POLICY)).policy_id == 11
    assert store.exists("/policies/new.qtab")

    assert ctrl.set_mode(Mode.HOLD)[0]
    bad = bytearray(policy_bytes(33))
    bad[60] ^= 0x55
    c.put("/policies/bad.qtab", bytes(bad))
    r = c.activate("/policies/bad.qtab")
    assert r[2] == Op.NAK
    (_sev, text), = server.drain_texts()
    assert text.startswith("policy refused: policy rejected:") and "CRC32" in text
    assert ctrl.policy.policy_id == 11

    assert c.activate("/policies/new.qtab")[2] == Op.ACK
    assert ctrl.policy.policy_id == 22 and ctrl.last_known_good.policy_id == 11
    assert load_policy(store.resolve(ACTIVE_POLICY)).policy_id == 22
    assert load_policy(store.resolve(LAST_GOOD_POLICY)).policy_id == 11
    assert not store.exists("/policies/new.qtab")


def test_boot_loads_the_newest_valid_policy(tmp_path):
    store = Storage(tmp_path / "root")
    store.write_atomic(ACTIVE_POLICY, policy_bytes(5))
    store.write_atomic(LAST_GOOD_POLICY, policy_bytes(4))

    def boot():
        for path in boot_policy_candidates(Storage(store.root)):
            try:
                return load_policy(path).policy_id
            except PolicyError:
                continue
        return None

    assert boot() == 5
    store.resolve(ACTIVE_POLICY).write_bytes(policy_bytes(5)[:-3])  # damaged behind the robot's back
    assert boot() == 4
    store.resolve(ACTIVE_POLICY).unlink()
    assert boot() == 4
