"""A kind is one package, imported when a policy of it is loaded (issue 45): a robot running the
shipped cell policy, from `qnav-robot`'s own loader through a controller driving toward a goal,
has imported no module of the sector kind (its planner, memory, guard) nor of sector-memory
(the Bug memory, its route); the sector policy imports its own package and not sector-memory's.
Each run is a fresh interpreter, so nothing another test imported counts."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from firmware_py import kinds

ROOT = Path(__file__).resolve().parents[2]

# as `qnav-robot --policy SPEC` loads it (cli._load_policy), then a controller armed and driving
# toward a free point of the policy's map for 40 ticks on the kinematic rig
SCRIPT = r"""
import json, sys
from firmware_py import cli, robot_spec
from firmware_py.control.controller import Controller
from firmware_py.vehicle import CtrlState
from firmware_py.vehicle import VehicleConfig
from tests.support.controller_rig import Kinematic, Rig

policy = cli._load_policy(cli.build_parser().parse_args(["--policy", sys.argv[1]]))
grid = policy.map_grid
free = [(c, r) for r in range(grid.height) for c in range(grid.width) if not grid.occupied(c, r)]
goal = policy.goals[0] if policy.goals else free[-1]
start = next(c for c in free if 2 <= abs(c[0] - goal[0]) + abs(c[1] - goal[1]) <= 4)
x, y = robot_spec.cell_center_mm(*start, grid.height, grid.cell_mm)
ctrl = Controller(VehicleConfig(), policy, start_pose_mm=(x, y, 0), localise=False)
rig = Rig(ctrl, Kinematic(x, y, 0.0))
rig.tick()
assert ctrl.arm() == (True, ""), ctrl.arm()
assert ctrl.go_to(*robot_spec.cell_center_mm(*goal, grid.height, grid.cell_mm)) == (True, "")
driving = 0
for _ in range(40):
    rig.tick()
    driving += ctrl.state == CtrlState.DRIVING
moved = any(c is not None and (c.left_mm_s, c.right_mm_s) != (0, 0) for c in rig.commands)
print(json.dumps({"kind": policy.kind, "driving": driving, "moved": moved,
                  "modules": sorted(m for m in sys.modules if m.startswith("firmware_py.kinds"))}))
"""


def _run(spec: str) -> dict:
    out = subprocess.run([sys.executable, "-c", SCRIPT, spec], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _packages(modules: list[str]) -> set[str]:
    return {m.split(".")[2] for m in modules if m.count(".") >= 2}


@pytest.mark.parametrize(("spec", "kind", "imported", "not_imported"), [
    ("policies:paper10_cell", "cell", {"cell"}, {"sector", "sector_memory"}),
    ("policies:sector", "sector", {"sector"}, {"cell", "sector_memory"}),
    ("policies:sector_memory", "sector-memory", {"sector_memory"}, {"cell", "sector"}),
])
def test_a_robot_imports_only_its_policys_kind(spec, kind, imported, not_imported):
    res = _run(spec)
    assert res["kind"] == kind and res["driving"] > 0 and res["moved"], res
    packages = _packages(res["modules"])
    assert imported <= packages, res["modules"]
    assert not packages & not_imported, f"{spec} imported {sorted(packages & not_imported)}: {res['modules']}"


def test_a_kinds_metadata_on_another_kinds_policy_is_refused():
    """`local_planner` is the sector kind's (its parse_metadata reads it): a cell policy carrying it is
    refused by name, as before the kind parsed its own metadata, without the loader importing the sector
    package to know."""
    from array import array

    from firmware_py.kinds.cell.encoder import CellEncoder
    from firmware_py.policy import PolicyError, dump_policy, load_policy

    enc = CellEncoder(2, 1)
    data = dump_policy(enc, array("b", [0] * (enc.n_states * enc.n_actions)), "int8", 0.1, goals=[(1, 0)],
                       cell_mm=500, metadata={"local_planner": {}})
    with pytest.raises(PolicyError, match="local_planner is sector policy metadata, not for a cell policy"):
        load_policy(data)


def test_names_lists_every_shipped_kind_and_lookups_agree():
    assert set(kinds.SHIPPED) <= set(kinds.names())
    for name, (code, module) in kinds.SHIPPED.items():
        kind = kinds.of_name(name)
        assert kinds.of_code(code) is kind and kind.code == code
        assert sys.modules[module].KIND is kind  # type: ignore[attr-defined]
    with pytest.raises(KeyError, match="known: cell, sector, sector-memory"):
        kinds.of_name("nope")
