"""Dependencies split by program, and an installed qnav that needs no checkout.

`pip install qnav` is the robot: `qnav-robot` imports and runs with none of
the station packages; `qnav` and `qnav-sim` refuse in one line naming
`pip install 'qnav[station]'`; `--can remote:` without python-can-remote
names `qnav[hil]`. The fast tests hide the station packages from a child
interpreter with an import blocker (the shared venv has them all); the slow
one installs the tree, no extras, into a fresh venv and runs the programs.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from firmware_py.shipped_policies import (
    ShippedPolicyError,
    resolve_policy_spec,
    shipped_policies_dir,
    shipped_policy,
    shipped_policy_names,
)
from ground_station.extras import INSTALL_HINT, STATION_IMPORTS
from ground_station.subprocs import free_udp_port
from tests.support.robot_venv import ROBOT_DISTS

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
STATION_ONLY = ("numpy", "numba", "pymunk", "textual", "matplotlib", "gymnasium", "tqdm")

BLOCKER = """
import sys
BLOCKED = set({blocked!r})
class Blocker:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}} (blocked)", name=name)
        return None
sys.meta_path.insert(0, Blocker())
"""


def _dist_name(requirement: str) -> str:
    for i, ch in enumerate(requirement):
        if ch in "<>=!~;[ ":
            return requirement[:i].lower()
    return requirement.lower()


def _run_blocked(blocked: tuple[str, ...], body: str, timeout: float = 60) -> subprocess.CompletedProcess:
    code = BLOCKER.format(blocked=blocked) + body
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def test_base_dependencies_are_exactly_what_firmware_py_imports():
    base = {_dist_name(r) for r in PYPROJECT["project"]["dependencies"]}
    assert base == set(ROBOT_DISTS)
    third_party = set()
    for path in (ROOT / "firmware_py").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            else:
                continue
            third_party |= {n.split(".")[0] for n in names} - set(sys.stdlib_module_names) - {"firmware_py"}
    # pyserial is not imported by name: python-can's slcan bus and pymavlink's serial links use it;
    # dronecan is the optional extra of the dronecan backends (tests/test_layering.py: only they import it)
    assert third_party | {"serial"} == set(ROBOT_DISTS.values()) | {"dronecan"}
    assert {_dist_name(r) for r in PYPROJECT["project"]["optional-dependencies"]["dronecan"]} == {"dronecan"}


def test_extras_split_station_hil_cluster_and_dev():
    extras = {k: {_dist_name(r) for r in v} for k, v in PYPROJECT["project"]["optional-dependencies"].items()}
    assert extras["station"] == set(STATION_IMPORTS)  # the guard checks every station package
    assert extras["hil"] == {"python-can-remote"}
    assert {"pytest", "ruff"} <= extras["dev"]
    assert not (extras["station"] | extras["hil"]) & set(ROBOT_DISTS)
    assert PYPROJECT["project"]["license"] == "MIT"  # SPDX string: no setuptools deprecation banner
    assert "setuptools>=77" in PYPROJECT["build-system"]["requires"]
    assert extras["cluster"] == {"ray"}  # Ray only for campaigns, imported lazily by ground_station.lab.campaign
    assert "[station,dev,cluster]" in (ROOT / "Makefile").read_text()


def test_robot_runs_without_any_station_package(tmp_path):
    # --help, then a real run: virtual CAN, a shipped policy by name, the MAVLink node on UDP, storage
    port = free_udp_port()
    stats = tmp_path / "stats.json"
    run = ["--can", "virtual:pkg", "--policy", "policies:paper10_cell", "--storage", str(tmp_path / "store"),
           "--mavlink", f"udpin:127.0.0.1:{port}", "--duration", "0.3", "--stats-json", str(stats), "-q"]
    body = f"""
import contextlib, io
from firmware_py.cli import main
out = io.StringIO()
with contextlib.redirect_stdout(out):
    try:
        main(["--help"])
    except SystemExit as exc:
        assert exc.code == 0, exc.code
assert "--policy" in out.getvalue() and "--mavlink" in out.getvalue()
assert main({run!r}) == 0
bad = sorted({{m.split(".")[0] for m in sys.modules}} & BLOCKED)
print("loaded:", bad)
"""
    blocked = (*STATION_ONLY, "can_remote", "ground_station", "sim_bridge", "qnav_policies")
    proc = _run_blocked(blocked, body)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().endswith("loaded: []"), proc.stdout
    summary = json.loads(stats.read_text())
    assert summary["ticks"] > 0 and summary["state"] == "STANDBY"


def test_robot_on_the_hil_hub_without_python_can_remote_names_the_hil_extra():
    proc = _run_blocked(("can_remote",), "from firmware_py.cli import main\n"
                        "sys.exit(main(['--can', 'remote:ws://127.0.0.1:9/', '--duration', '0.1', '-q']))")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "python-can-remote" in lines[0] and "pip install 'qnav[hil]'" in lines[0], lines


@pytest.mark.parametrize("module", ["ground_station.cli", "sim_bridge.cli"])
def test_station_programs_refuse_in_one_line_without_the_station_extra(module):
    proc = _run_blocked(("numpy", "textual"), f"from {module} import main\nsys.exit(main(['--help']))")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "missing: numpy, textual" in lines[0] and INSTALL_HINT in lines[0]
    assert proc.stdout == ""  # refused before parsing: no help text, no traceback


def test_shipped_policies_resolve_by_name():
    assert shipped_policy_names() == sorted(p.stem for p in shipped_policies_dir().glob("*.qtab"))
    assert {"paper10_cell", "sector"} <= set(shipped_policy_names())
    assert shipped_policy("sector") == shipped_policy("sector.qtab") == shipped_policies_dir() / "sector.qtab"
    assert resolve_policy_spec("policies:sector") == shipped_policy("sector")
    assert resolve_policy_spec("policies/sector.qtab") == Path("policies/sector.qtab")  # a path stays a path
    for bad in ("nope", "../policies/sector", "", "policies/sector"):
        with pytest.raises(ShippedPolicyError, match="shipped: paper10_cell, sector"):
            shipped_policy(bad)


# The fresh venv without extras (pip install of the wheel, no station packages): checked by
# tests/support/robot_venv.py on the venv docs/deploy.md makes, in
# tests/firmware_py/test_deploy_doc.py::test_tested_blocks_run_here (one install, not two: each cost
# the suite ~60 s).


def test_make_test_runs_every_test_folder_and_file():
    """`make test` splits the suite (everything on both cores, then the
    `wallclock` tests one at a time): every folder and top-level test file
    must be in one of its pytest lines, or new tests would silently not run
    in CI."""
    make = (ROOT / "Makefile").read_text()
    recipe = make[make.index("\ntest:"):]
    recipe = recipe[:recipe.index("\n\n")]
    for p in sorted((ROOT / "tests").iterdir()):
        if p.name in ("__init__.py", "support", "__pycache__") or p.name.startswith("."):
            continue
        if p.is_dir() or (p.suffix == ".py" and p.name.startswith("test_")):
            assert f"tests/{p.name}" in recipe, f"tests/{p.name} is not run by make test"
