"""qnav's global-localisation command over MAVLink (MAV_CMD_USER_1), through
real MAVLink frames to a MavNode driving the real controller."""

from __future__ import annotations

from firmware_py.control.controller import Controller
from firmware_py.mavlink.commands import CMD_LOCALISE_GLOBAL
from firmware_py.mavlink.dialect import mavlink2 as m
from firmware_py.mavlink.node import MavNode
from firmware_py.mavlink.params import ParamStore
from firmware_py.mavlink.signing import Signing
from firmware_py.policy import load_policy
from firmware_py.shipped_policies import shipped_policy


def _command(tmp_path, ctrl: Controller, *p: float) -> tuple[int, list[str]]:
    """Send COMMAND_LONG(CMD_LOCALISE_GLOBAL, p...) as bytes; (ACK result, STATUSTEXTs)."""
    node = MavNode(ctrl, ParamStore(tmp_path), Signing(tmp_path))
    node.boot(1_000_000, None)
    gcs = m.MAVLink(None, 255, 190)
    robot, decoder = m.MAVLink(None, 1, 1), m.MAVLink(None)
    params = list(p) + [0.0] * (7 - len(p))
    msg = m.MAVLink(None).parse_char(bytes(gcs.command_long_encode(1, 1, CMD_LOCALISE_GLOBAL, 0, *params).pack(gcs)))
    replies = [decoder.parse_char(bytes(r.pack(robot))) for r in node.handle(msg, 1_000_000)]
    (ack,) = [r for r in replies if r.get_type() == "COMMAND_ACK"]
    assert ack.command == CMD_LOCALISE_GLOBAL
    return ack.result, [r.text for r in replies if r.get_type() == "STATUSTEXT"]


def test_command_starts_global_localisation_and_goals_wait_for_it(tmp_path):
    ctrl = Controller(policy=load_policy(shipped_policy("sector")), start_pose_mm=(1250, 1250, 0))
    assert ctrl.status().localised
    result, _ = _command(tmp_path, ctrl, 0)
    assert result == m.MAV_RESULT_ACCEPTED
    assert ctrl.status().localiser == "global" and not ctrl.status().localised
    ctrl.armed = True  # the rest of _can_drive is covered by the controller tests
    ok, why = ctrl.go_to(4250, 4250)
    assert not ok and why.startswith("not localised")


def test_command_refusals_carry_the_reason(tmp_path):
    ctrl = Controller(policy=load_policy(shipped_policy("sector")), start_pose_mm=(1250, 1250, 0))
    result, text = _command(tmp_path, ctrl, 2)
    assert result == m.MAV_RESULT_DENIED and any("param1 must be 0" in t for t in text)
    assert ctrl.status().localised  # nothing changed
    off = Controller(policy=load_policy(shipped_policy("sector")), localise=False)
    result, text = _command(tmp_path / "off", off, 1)
    assert result == m.MAV_RESULT_DENIED and any("global localisation refused: no map" in t for t in text)
