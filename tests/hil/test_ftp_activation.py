"""FTP activation against the real controller: FtpServer's Rename onto
active.qtab calls Controller.activate_policy; refusals leave the old policy
driving; boot picks the newest valid file. A policy trained for another
control period is refused (both values in the reason), and so is a
CTRL_RATE_HZ change the active policy does not fit."""

from firmware_py.control.controller import Controller
from firmware_py.mavlink.ftp_server import HEADER, PAYLOAD_LEN, FtpServer, Nak, Op, parse
from firmware_py.policy import PolicyError, dump_policy, load_policy
from firmware_py.storage import ACTIVE_POLICY, LAST_GOOD_POLICY, Storage, boot_policy_candidates
from firmware_py.vehicle import CtrlState, Mode, VehicleConfig
from tests.support.controller_rig import Kinematic, Rig, sector_seek_policy


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
    assert ctrl.go_to(5000, 0) == (True, "")
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


def policy_for_period(policy_id, period_us):
    base = sector_seek_policy(policy_id=1)
    return dump_policy(base.encoder, base.table.tolist(), "int8", 0.5, policy_id=policy_id,
                       map_geometry=base.map_geometry, control_period_us=period_us)


def test_a_policy_for_another_control_period_is_refused_naming_both_and_last_good_is_kept(tmp_path):
    ctrl = Controller(VehicleConfig(), load_policy(policy_bytes(11)), start_pose_mm=(0, 0, 0))
    assert ctrl.cfg.control_period_us == 50_000
    store = Storage(tmp_path / "root")
    store.write_atomic(ACTIVE_POLICY, policy_bytes(11))
    store.write_atomic(LAST_GOOD_POLICY, policy_bytes(10))
    other = tmp_path / "other.qtab"
    other.write_bytes(policy_for_period(22, 40_000))
    # the core
    assert ctrl.activate_policy(str(other)) == (False, "policy control period 40000 us != robot 50000 us")
    assert ctrl.policy.policy_id == 11 and ctrl.last_known_good is None
    # over MAVLink FTP: NAK, the reason with both values, active and last-good untouched
    server = FtpServer(store, activate=ctrl.activate_policy)
    c = FtpClient(server)
    c.put("/policies/new.qtab", policy_for_period(22, 40_000))
    r = c.activate("/policies/new.qtab")
    assert r[2] == Op.NAK and r[7] == bytes([Nak.FAIL])
    assert server.drain_texts() == [(4, "policy refused: policy control period 40000 us != robot 50000 us")]
    assert ctrl.policy.policy_id == 11
    assert load_policy(store.resolve(ACTIVE_POLICY)).policy_id == 11
    assert load_policy(store.resolve(LAST_GOOD_POLICY)).policy_id == 10
    # a robot configured for 25 Hz takes it
    ctrl25 = Controller(VehicleConfig(control_rate_hz=25))
    assert ctrl25.activate_policy(str(other)) == (True, "")


def mav_param_set(node, name: str, value: float) -> tuple[list[str], float]:
    """PARAM_SET through real MAVLink frames; (STATUSTEXTs, the PARAM_VALUE echoed)."""
    from firmware_py.mavlink.dialect import mavlink2 as m

    gcs, robot, decoder = m.MAVLink(None, 255, 190), m.MAVLink(None, 1, 1), m.MAVLink(None)
    msg = m.MAVLink(None).parse_char(bytes(gcs.param_set_encode(1, 1, name.encode(), value, 6).pack(gcs)))
    replies = [decoder.parse_char(bytes(r.pack(robot))) for r in node.handle(msg, 1_000_000)]
    texts = [r.text for r in replies if r.get_type() == "STATUSTEXT"]
    (pv,) = [r for r in replies if r.get_type() == "PARAM_VALUE"]
    return texts, pv.param_value


def test_ctrl_rate_change_that_the_active_policy_does_not_fit_is_refused(tmp_path):
    from firmware_py.mavlink.node import MavNode
    from firmware_py.mavlink.params import ParamStore
    from firmware_py.mavlink.signing import Signing

    ctrl = Controller(VehicleConfig(), load_policy(policy_bytes(11)))
    node = MavNode(ctrl, ParamStore(tmp_path), Signing(tmp_path))
    node.boot(0)
    texts, value = mav_param_set(node, "CTRL_RATE_HZ", 25)
    assert value == 20 and ctrl.cfg.control_rate_hz == 20 and ctrl.policy.policy_id == 11
    assert "".join(texts) == "param set refused: CTRL_RATE_HZ=25: policy control period 50000 us != robot 40000 us"
    # nothing stored (the params folder holds only the robot uid made at boot)
    assert ParamStore(tmp_path).load() == [] and not (tmp_path / "params" / "params.json").exists()
    texts, value = mav_param_set(node, "CTRL_RATE_HZ", 20)  # unchanged is fine
    assert value == 20 and texts == []
    # a robot with no policy may change its rate, then takes a policy for the new period only
    bare = Controller(VehicleConfig())
    bare_node = MavNode(bare, ParamStore(tmp_path / "bare"), Signing(tmp_path / "bare"))
    bare_node.boot(0)
    texts, value = mav_param_set(bare_node, "CTRL_RATE_HZ", 25)
    assert value == 25 and texts == [] and bare.cfg.control_period_us == 40_000
    p50, p40 = tmp_path / "p50.qtab", tmp_path / "p40.qtab"
    p50.write_bytes(policy_bytes(21))
    p40.write_bytes(policy_for_period(22, 40_000))
    assert bare.activate_policy(str(p50)) == (False, "policy control period 50000 us != robot 40000 us")
    assert bare.activate_policy(str(p40)) == (True, "")


def test_stored_rate_that_the_boot_policy_does_not_fit_unloads_it_with_the_reason(tmp_path):
    from firmware_py.mavlink.node import MavNode
    from firmware_py.mavlink.params import ParamStore
    from firmware_py.mavlink.signing import Signing

    stored = ParamStore(tmp_path)
    assert stored.set("CTRL_RATE_HZ", 25) == (True, "")  # saved while no policy was active
    ctrl = Controller(VehicleConfig(), load_policy(policy_bytes(11)))
    MavNode(ctrl, ParamStore(tmp_path), Signing(tmp_path)).boot(0)
    assert ctrl.cfg.control_period_us == 40_000 and ctrl.policy is None  # never runs at a foreign period
    assert [e.text for e in ctrl.drain_events()] == ["policy control period 50000 us != robot 40000 us"]
