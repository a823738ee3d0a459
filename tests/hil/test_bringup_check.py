"""`qnav-robot --check` against the sim (paced at real time on a hub): every board the profile expects
is listed with its state, a missing one fails the check naming it, and `--check-motors` finds a wheel
whose motor the sim mounts the other way round, through qnav's wheel encoders and, for ODrive's and a
DroneCAN ESC's motor encoders, through the range sensors, while the other wheel reads forward
(docs/deploy.md). One run per backend: each checks the board list, the flipped wheel and the good one."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from ground_station.canhub import CanHub

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
PROFILES = ROOT / "firmware_py" / "profiles"


def _check(sim_profile: str, robot_profile: str, *extra_sim: str, motors: bool = True) -> tuple[int, str]:
    with CanHub("check") as hub:
        sim = subprocess.Popen([BIN / "qnav-sim", "--map", "paper10", "--can", hub.spec, "--realtime", "--duration",
                                "60", "--start", "2.75,1.75,0", "-q", "--profile", PROFILES / sim_profile,
                                *extra_sim], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True)
        try:
            assert sim.stderr is not None
            first = sim.stderr.readline()  # the sim says where it runs once its bus is open
            assert first.startswith("qnav-sim: paper10"), first
            run = subprocess.run([BIN / "qnav-robot", "--check", "--check-listen", "1", *(["--check-motors"] if motors else []),
                                  "--profile", PROFILES / robot_profile, "--can", hub.spec],
                                 capture_output=True, text=True, timeout=60)
        finally:
            sim.send_signal(signal.SIGINT)
            sim.communicate(timeout=20)
    return run.returncode, run.stdout + run.stderr


BOARDS = {  # what each backend's boards look like in the report (the flipped-wheel runs below)
    "qnav.toml": ["ok       drive: qnav motor driver (node 34)"],
    "odrive.toml": ["ok       drive: left axis 0 (ODrive node 0): state IDLE, no error",
                    "ok       drive: right axis 1 (ODrive node 1): state IDLE, no error"],
    "dronecan.toml": ["ok       drive: left ESC 0, DroneCAN node 10: esc.Status", "ok       drive: right ESC 1, "
                      "DroneCAN node 11: esc.Status", *(f"info     DroneCAN node {n}: health OK" for n in (10, 11, 20))],
}


@pytest.mark.parametrize("profile, words", [
    ("qnav.toml", "PROBLEM  left wheel: turned BACKWARDS"),  # qnav's encoders count the wheel
    ("odrive.toml", "PROBLEM  left wheel: the robot turned the WRONG way"),  # ODrive's count the motor
    ("dronecan.toml", "PROBLEM  left wheel: the robot turned the WRONG way"),  # so does an ESC's rpm
])
def test_check_motors_finds_a_wheel_mounted_the_other_way_round(profile, words):
    if profile == "dronecan.toml":
        pytest.importorskip("dronecan", reason="the dronecan extra (pip install 'qnav[dronecan]')")
    code, out = _check(profile, profile, "--flip-wheel", "left")
    assert code == 1 and words in out and "flip drive.left_sign" in out, out
    for line in BOARDS[profile]:  # every board listed with its node id and state
        assert line in out, out
    for i in range(8):
        assert f"ok       range sensor {i} at " in out
    # the right wheel is mounted as the profile says: forward, or (a motor's encoder, the ranges unsure) by eye
    assert "ok       right wheel: forward" in out or "info     right wheel: motor encoder" in out


def test_check_names_a_board_that_does_not_answer():
    # the robot expects qnav's motor driver; the bus has two ODrive axes instead
    code, out = _check("odrive.toml", "qnav.toml", motors=False)
    assert code == 1, out
    assert "MISSING  drive: qnav motor driver (node 34): not heard (no MotorStatus)" in out
    assert "info     unknown frame id 0x1 (standard)" in out  # ODrive node 0's heartbeat, named as unknown
    assert "qnav-robot --check: 2 problem(s)" in out
