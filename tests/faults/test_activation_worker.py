"""Issue 29 finding 3: a policy's map chooses how much work activation is.

A legal map can be large (the loader caps cells and, now, millimetres); the
localiser's likelihood field for it is built on a worker thread, so the FTP
Rename that activates it returns at once with no reply, the running policy
keeps driving, and the reply (ACK, or NAK with the reason) follows from
`FtpServer.poll` when the worker is done. Driven on the real Controller and
FtpServer, without sockets."""

from __future__ import annotations

import time
from array import array

import pytest

from firmware_py import policy as fmt
from firmware_py.control.controller import Controller
from firmware_py.mapdata import MAX_SIDE_MM, MIN_CELL_MM
from firmware_py.mavlink.ftp_server import FtpServer, Op, parse
from firmware_py.shipped_policies import resolve_policy_spec
from firmware_py.storage import ACTIVE_POLICY, Storage
from firmware_py.vehicle import PendingActivation, VehicleConfig
from tests.firmware_py.test_ftp_server import Client, ack, nak, put


def _sector_with_map(width: int, cell_mm: int) -> bytes:
    """The shipped sector table carrying a walled width x width map (map-agnostic
    kind: the map is for the localiser only)."""
    base = fmt.load_policy(resolve_policy_spec("policies:sector"))
    rows = ["@" * width] + ["@" + "." * (width - 2) + "@"] * (width - 2) + ["@" * width]
    meta = {**base.metadata, "map_grid": rows}
    table = array(fmt.DTYPES[fmt.DTYPE_CODES[base.dtype]][1], base.table)
    return fmt.dump_policy(base.encoder, table, base.dtype, base.scale, goals=base.goals, cell_mm=cell_mm,
                           metadata=meta, control_period_us=base.control_period_us,
                           map_geometry=fmt.MapGeometry(cell_mm, width, width))


@pytest.fixture
def rig(tmp_path):
    ctrl = Controller(VehicleConfig(), fmt.load_policy(resolve_policy_spec("policies:sector")))
    server = FtpServer(Storage(tmp_path / "root", quota_bytes=1_000_000), activate=ctrl.begin_activation)
    return ctrl, server, Client(server)


def _rename(c: Client, name: str) -> list:
    return c.send(Op.RENAME, f"/policies/{name}\0{ACTIVE_POLICY}\0".encode())


def test_the_largest_legal_map_activates_off_the_link_thread(rig):
    ctrl, server, c = rig
    old_id = ctrl.policy.policy_id
    width = 120  # the metadata limit (16 KiB) holds the widest map: the base metadata's room left
    while True:
        try:
            data = _sector_with_map(width, MAX_SIDE_MM // width)
            break
        except ValueError:
            width -= 1
    assert width >= 110
    put(c, "/policies/big.qtab", data)
    assert _rename(c, "big.qtab") == []  # no reply yet: the field is being built on a worker
    assert _rename(c, "big.qtab") == []  # a retry meanwhile starts nothing and gets no reply
    assert ctrl.policy.policy_id == old_id  # the running policy keeps driving meanwhile
    replies: list = []
    deadline = time.monotonic() + 60
    while not replies and time.monotonic() < deadline:
        replies = server.poll(c.now)
        time.sleep(0.01)
    (owner, reply), = replies
    assert owner == c.owner and ack(parse(reply))
    assert parse(reply)[0] == c.seq + 1  # it answers the newest retry
    new = fmt.load_policy(data)
    assert ctrl.policy.policy_id == new.policy_id and ctrl.last_known_good.policy_id == old_id
    assert ctrl.loc is not None and ctrl.loc.grid == new.map_grid
    assert server.storage.resolve(ACTIVE_POLICY).read_bytes() == data  # the slots moved only now
    assert any("policy active" in t for _s, t in server.drain_texts())
    assert ctrl.loc.field.nx * ctrl.loc.field.ny <= 300_000


def test_a_map_beyond_the_limits_is_refused_with_the_reason_and_nothing_changes(rig):
    ctrl, server, c = rig
    old_id = ctrl.policy.policy_id
    for width, cell_mm, needle in ((100, 600, f"up to {MAX_SIDE_MM} mm a side"),
                                   (20, MIN_CELL_MM - 1, f"allowed {MIN_CELL_MM}..")):
        put(c, "/policies/huge.qtab", _sector_with_map(width, cell_mm))
        (reply,) = _rename(c, "huge.qtab")  # the loader refuses at once: a reply now
        assert nak(reply, 1), reply  # Nak.FAIL
        texts = [t for _s, t in server.drain_texts()]
        assert any(needle in t for t in texts), texts
        assert ctrl.policy.policy_id == old_id
        assert not server.storage.resolve(ACTIVE_POLICY).exists()


def test_a_worker_that_fails_is_a_refusal_and_a_slow_one_times_out(rig, monkeypatch):
    ctrl, server, c = rig
    old_id = ctrl.policy.policy_id
    put(c, "/policies/m.qtab", _sector_with_map(30, 500))

    def no_memory(_pol):
        raise MemoryError

    monkeypatch.setattr(ctrl, "_new_localiser", no_memory)
    assert _rename(c, "m.qtab") == []
    deadline = time.monotonic() + 10
    while not (replies := server.poll(c.now)) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert nak(parse(replies[0][1]), 1)
    assert any("does not fit in memory" in t for _s, t in server.drain_texts())
    assert ctrl.policy.policy_id == old_id
    # a worker that never finishes: refused after the activation timeout, its late result dropped
    never = PendingActivation()
    monkeypatch.setattr(ctrl, "begin_activation", lambda _path: never)
    server.activate = ctrl.begin_activation
    assert _rename(c, "m.qtab") == []
    assert server.poll(c.now + server.activation_timeout_us) == []
    (owner, reply), = server.poll(c.now + server.activation_timeout_us + 1)
    assert nak(parse(reply), 1) and never.cancelled
    assert any("not ready within 20 s" in t for _s, t in server.drain_texts())
    assert ctrl.policy.policy_id == old_id and not server.storage.resolve(ACTIVE_POLICY).exists()
