"""Issue 15 items 7 and 9 across the programs: the sim and the robot say
what they wait for, `--help` shows every default, run folders are named
automatically, `qnav eval` takes the map from the run, integer options take
1e6, and the demo's CAN log is also written as a candump -L file that
`cantools decode` reads."""

from __future__ import annotations

import argparse
import json
import os
import select
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest

from firmware_py import cli as robot_cli
from ground_station.canhub import CanHub
from ground_station.monitor.canlog import analyse_candump, write_candump
from ground_station.subprocs import stop_process
from sim_bridge import cli as sim_cli

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


def test_lockstep_sim_without_controller_says_what_it_waits_for():
    proc = subprocess.run([BIN / "qnav-sim", "--map", "paper10", "--can", "virtual:gcs-lonely", "--lockstep",
                           "--start-timeout", "2.5", "-q"], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert proc.returncode != 0
    assert "waiting for a controller to answer SimTick 0" in proc.stderr, proc.stderr
    assert "qnav-robot --lockstep" in proc.stderr


@pytest.mark.slow
def test_robot_says_when_the_lockstep_sim_goes_quiet(tmp_path):
    with CanHub("gcsquiet") as hub:
        robot = subprocess.Popen(
            [BIN / "qnav-robot", "--can", hub.spec, "--lockstep", "--policy", "policies:paper10_cell",
             "--start", "0.25,0.25,0", "--mavlink", "none", "-q"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT)
        try:
            sim = subprocess.run([BIN / "qnav-sim", "--map", "paper10", "--can", hub.spec, "--lockstep",
                                  "--duration", "2", "--start", "0.25,0.25,0", "-q"],
                                 capture_output=True, text=True, timeout=90, cwd=ROOT)
            assert sim.returncode == 0, sim.stderr
            # SIM_QUIET_S (3 s) after the last SimTick the robot says so: its stderr, read until then
            err = ""
            deadline = time.monotonic() + 15
            while "no SimTick from the sim" not in err and time.monotonic() < deadline and robot.poll() is None:
                if select.select([robot.stderr], [], [], 0.2)[0]:
                    err += os.read(robot.stderr.fileno(), 65536).decode(errors="replace")
        finally:
            stop_process(robot, timeout_s=10)
        err += robot.stderr.read() if robot.stderr else ""
    assert "no SimTick from the sim" in err and "sim time stands still at 1.95 s" in err  # the last tick of 2 s, err


@pytest.mark.parametrize("build", [robot_cli.build_parser, sim_cli.build_parser])
def test_help_shows_every_default(build):
    parser = build()
    text = parser.format_help()
    for action in parser._actions:
        if not action.option_strings or isinstance(action, argparse._HelpAction):
            continue
        if action.default in (None, False, argparse.SUPPRESS):
            continue
        help_text = action.help or ""
        assert "default" in help_text or f"(default: {action.default})" in " ".join(text.split()), \
            f"{action.option_strings[0]}: default {action.default!r} not shown"


def _qnav(*argv: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ground_station.cli", *argv], capture_output=True, text=True,
                          timeout=600, cwd=cwd, env={**_env(), "PYTHONPATH": str(ROOT)})


def _env() -> dict[str, str]:
    return dict(os.environ)


def test_train_names_its_run_folder_and_eval_finds_the_map(tmp_path):
    out = _qnav("train", "--map", "paper10", "--steps", "2e4", "--seed", "3", "--quiet", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    runs = list((tmp_path / "runs").iterdir())
    assert len(runs) == 1 and runs[0].name.startswith("paper10-cell-s3-"), runs
    meta = json.loads((runs[0] / "meta.json").read_text())
    assert meta["steps"] == 20_000
    ev = _qnav("eval", str(runs[0]), "--json", cwd=tmp_path)
    assert ev.returncode == 0, ev.stderr
    assert json.loads(ev.stdout)["encoding"] == "cell"
    bad = _qnav("train", "--steps", "1.5", "--quiet", cwd=tmp_path)
    assert bad.returncode == 2 and "expected a whole number, got '1.5'" in bad.stderr
    nometa = _qnav("eval", str(tmp_path), cwd=tmp_path)
    assert nometa.returncode == 2 and "meta.json: no such file" in nometa.stderr


def test_candump_copy_of_a_blf_is_read_by_cantools_and_qnav_report(tmp_path):
    from firmware_py import can_protocol as cp

    blf = tmp_path / "can.blf"
    writer = can.BLFWriter(str(blf))
    frames = [cp.encode("SimTick", {"Tick_Counter": i, "Tick_SimTimeUs": 50_000 * i}) for i in range(5)]
    for i, msg in enumerate(frames):
        msg.timestamp = 0.05 * i
        writer.on_message_received(msg)
    writer.stop()
    log = tmp_path / "can.log"
    assert write_candump(blf, log) == 5
    assert analyse_candump(log)["frames"] == 5
    dec = subprocess.run([BIN / "cantools", "decode", str(ROOT / "firmware_py" / "qnav.dbc")],
                         input=log.read_text(), capture_output=True, text=True, timeout=60)
    assert dec.returncode == 0, dec.stderr
    assert dec.stdout.count("SimTick(") == 5 and "Tick_Counter: 4" in dec.stdout, dec.stdout


def test_candump_report_counts_a_resent_tick_and_its_second_answer_once(tmp_path):
    """Lockstep under load: the sim resends a SimTick whose answer is late, and the robot may
    answer it twice. The log then holds 3 SimTick and 3 MotorCommand frames for 2 ticks."""
    from firmware_py import can_protocol as cp

    def line(t: float, msg) -> str:
        return f"({t:.6f}) vcan0 {msg.arbitration_id:03X}#{bytes(msg.data).hex().upper()}"

    tick = [cp.encode("SimTick", {"Tick_Counter": n, "Tick_SimTimeUs": n * 50_000}) for n in (0, 0, 1)]
    cmd = [cp.encode("MotorCommand", {"Cmd_LeftSpeed": 100, "Cmd_RightSpeed": 100, "Cmd_Counter": n})
           for n in (0, 0, 1)]
    log = tmp_path / "resend.log"
    log.write_text("\n".join(line(i * 0.01, m) for i, m in enumerate(
        [tick[0], tick[1], cmd[0], cmd[1], tick[2], cmd[2]])) + "\n")
    s = analyse_candump(log)
    assert s["sim_ticks"] == 2 and s["sim_tick_resends"] == 1 and s["sim_tick_gaps"] == 0
    assert s["motor_commands"]["count"] == 2 and s["motor_commands"]["repeated"] == 1
    assert s["per_sim_tick"]["MotorCommand"] == 1.0 and s["by_name"]["SimTick"] == 3
