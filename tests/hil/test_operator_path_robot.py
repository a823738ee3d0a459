"""Issue 46's items that need the robot's answers, against a real `qnav-robot`
(python-can virtual bus, MAVLink over UDP loopback on a free port): policy ids
exact and in the same form in `param get` and `param list` (float32 on the wire
rounds a 32-bit id), and `qnav mode MANUAL` as MAVProxy users type it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from firmware_py.policy import load_policy
from tests.support.cli import idle_robot
from tests.support.cli import run_qnav as qnav

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    with idle_robot(tmp_path_factory.mktemp("robot")) as url:
        yield url


def test_policy_id_is_exact_and_the_same_in_get_and_list(robot):
    policy = load_policy(ROOT / "policies" / "paper10_cell.qtab")
    pid, pcrc = f"0x{policy.policy_id:08x}", f"0x{policy.crc:08x}"
    code, out, err = qnav("param", "get", "POLICY_ID", "--mavlink", robot, "--no-tlog", "--timeout", "20")
    assert code == 0, out + err
    assert out == f"POLICY_ID {pid}\n", out
    code, out, err = qnav("param", "get", "POLICY_CRC", "--mavlink", robot, "--no-tlog", "--timeout", "20")
    assert code == 0 and out == f"POLICY_CRC {pcrc}\n", out + err
    code, out, err = qnav("param", "list", "--no-descriptions", "--mavlink", robot, "--no-tlog", "--timeout", "20")
    assert code == 0, out + err
    rows = {ln.split()[0]: ln.split()[1] for ln in out.splitlines() if ln.strip()}
    assert rows["POLICY_ID"] == pid and rows["POLICY_CRC"] == pcrc, out
    code, out, err = qnav("param", "list", "--json", "--mavlink", robot, "--no-tlog", "--timeout", "20")
    assert code == 0 and json.loads(out)["POLICY_ID"] == policy.policy_id, out + err


def test_mode_takes_the_names_mavproxy_users_type(robot):
    code, out, err = qnav("mode", "MANUAL", "--mavlink", robot, "--no-tlog", "--timeout", "20")
    assert code == 0 and out == "mode manual\n", out + err
    code, out, err = qnav("mode", "Hold", "--mavlink", robot, "--no-tlog", "--timeout", "20")
    assert code == 0 and out == "mode hold\n", out + err
