"""What a venv with qnav installed without extras must be: the robot and nothing of the station.

Checked on the venv docs/deploy.md's own commands make (tests/firmware_py/test_deploy_doc.py): the
wheel built on the laptop, installed into a fresh venv as on the Pi.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from ground_station.extras import INSTALL_HINT, STATION_IMPORTS

# the robot's distributions -> their import names (tests/test_packaging.py checks pyproject against them)
ROBOT_DISTS = {"python-can": "can", "cantools": "cantools", "pymavlink": "pymavlink", "pyserial": "serial"}
STATION_ONLY = {"numpy", "numba", "pymunk", "textual", "matplotlib", "gymnasium", "python-can-remote"}


def check_robot_venv(bindir: Path, env: dict[str, str], cwd: Path) -> None:
    """Assert what `bindir`'s venv (qnav installed without extras) holds and does."""
    listed = subprocess.run([str(bindir / "python"), "-m", "pip", "list", "--format", "json"],
                            capture_output=True, text=True, timeout=60, env=env, check=True)
    installed = {d["name"].lower() for d in json.loads(listed.stdout)}
    assert set(ROBOT_DISTS) <= installed and "qnav" in installed, installed
    assert not installed & STATION_ONLY, installed & STATION_ONLY

    def run(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([str(bindir / argv[0]), *argv[1:]], capture_output=True, text=True,
                              timeout=60, env=env, cwd=cwd)

    assert run("qnav-robot", "--help").returncode == 0
    # the shipped policy comes from site-packages (qnav_policies), not from a checkout
    where = run("python", "-c", "from firmware_py.shipped_policies import shipped_policy; print(shipped_policy('sector'))")
    assert where.returncode == 0 and "site-packages/qnav_policies/sector.qtab" in where.stdout, where.stderr
    robot = run("qnav-robot", "--can", "virtual:pkg", "--policy", "policies:sector", "--mavlink", "none",
                "--duration", "0.2", "-q")
    assert robot.returncode == 0, robot.stderr
    # the robot's deployment pieces come with it: the systemd unit, the example profiles, the odrive backend
    unit = run("qnav-robot", "--print-unit")
    assert unit.returncode == 0 and "Type=notify" in unit.stdout
    profiles = run("python", "-c", "from importlib import resources; "
                                   "print(resources.files('firmware_py') / 'profiles')").stdout.strip()
    check = run("qnav-robot", "--check", "--check-listen", "0.3", "--profile", f"{profiles}/odrive.toml",
                "--can", "virtual:pkg")
    assert check.returncode == 1 and "MISSING  drive: left axis 0 (ODrive node 0): not heard" in check.stdout
    # a dronecan profile without the optional extra: one line saying what to install, exit 2
    dc = run("qnav-robot", "--profile", f"{profiles}/dronecan.toml", "--can", "virtual:pkg", "--mavlink", "none",
             "--duration", "0.2")
    assert dc.returncode == 2 and dc.stderr.strip().splitlines() == [
        f"qnav-robot: error: --profile {profiles}/dronecan.toml: the dronecan backends need the dronecan library: "
        "pip install 'qnav[dronecan]'"], dc.stderr
    for prog in ("qnav", "qnav-sim"):
        refused = run(prog, "--help")
        assert refused.returncode == 2 and refused.stderr.strip().splitlines() == [
            f"{prog}: error: needs the ground station packages (missing: "
            f"{', '.join(STATION_IMPORTS)}): {INSTALL_HINT}"], refused.stderr
