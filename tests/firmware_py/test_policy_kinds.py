"""The policy-kind contract (firmware_py.kinds): a kind defined and registered by
this test alone (its encoder, its encoder section, its decisions) is written by
the one writer, read back by the robot's loader and driven by the controller,
with no change to controller, loader or CLI code; and those modules name no kind.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from firmware_py import kinds
from firmware_py.kinds.base import PolicyKind
from firmware_py.policy import MapGeometry, PolicyError, dump_policy, load_policy
from tests.support.toy_kind import (
    ACTIONS,
    ROBOT_KIND,
    SpinDriver,
    SpinEncoder,
    _unpack,
    drive,
    unregister_robot_kind,
)

ROOT = Path(__file__).resolve().parents[2]
TOY = ROBOT_KIND
TOY_ACTIONS = ACTIONS


@pytest.fixture
def toy_kind():
    kinds.register(TOY)
    try:
        yield TOY
    finally:
        unregister_robot_kind(TOY.name)


def _toy_policy_bytes() -> bytes:
    # state 0 (clear): forward; state 1 (near): turn
    from array import array

    return dump_policy(SpinEncoder(), array("b", [50, 0, 0, 50]), "int8", 0.01,
                       map_geometry=MapGeometry(500, 10, 10))


def test_a_kind_registered_by_the_test_loads_and_drives_the_controller(toy_kind):
    pol = load_policy(_toy_policy_bytes())
    assert pol.kind == "toy-spin" and pol.encoder == SpinEncoder()
    (clear, st_clear), (blocked, st_blocked) = drive(pol)
    assert clear == TOY_ACTIONS[0] and st_clear.state_index == 0 and st_clear.action == 0
    assert blocked == TOY_ACTIONS[1]  # something close ahead: the toy's table turns
    assert st_blocked.state_index == 1 and st_blocked.q_row == (0, 50)


def test_registry_refuses_clashes_and_removed_codes_and_forgets_on_unregister(toy_kind):
    with pytest.raises(ValueError, match="clashes"):
        kinds.register(PolicyKind(name="toy-spin", code=201, actions=TOY_ACTIONS, unpack=_unpack,
                                  pack=TOY.pack, driver=SpinDriver))
    with pytest.raises(ValueError, match="sector-unmapped"):
        kinds.register(PolicyKind(name="other", code=5, actions=TOY_ACTIONS, unpack=_unpack,
                                  pack=TOY.pack, driver=SpinDriver))
    data = _toy_policy_bytes()
    unregister_robot_kind("toy-spin")
    with pytest.raises(PolicyError, match="unknown encoder kind 200"):
        load_policy(data)
    kinds.register(TOY)  # the fixture unregisters it again
    assert "toy-spin" in kinds.names() and kinds.of_code(200) is TOY


@pytest.mark.parametrize("module", ["firmware_py/control/controller.py", "firmware_py/control/state.py",
                                    "firmware_py/policy.py", "firmware_py/cli.py"])
def test_controller_loader_and_cli_name_no_kind(module):
    """A kind-specific branch (an encoder class, a kind's name, isinstance on an encoder) in
    these modules would break the contract: kinds are reached through the registry only."""
    code = "\n".join(line.split("#")[0] for line in (ROOT / module).read_text().splitlines()
                     if not line.lstrip().startswith(("#", '"', "'")))
    named = re.findall(r"CellEncoder|SectorEncoder|GridBugEncoder|GridBugMemory|isinstance\([^)]*\.encoder"
                       r"|[\"'](cell|sector|sector-memory)[\"']", code)
    assert named == [], f"{module} names a kind: {named}"
