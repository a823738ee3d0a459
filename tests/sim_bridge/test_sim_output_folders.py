"""`qnav-sim --log run/can.blf` as docs/hil.md writes it: a missing run/ folder
is created before the run (it used to fail with "log directory does not
exist"), and a folder that cannot be made is a one-line error up front."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import can

ROOT = Path(__file__).resolve().parents[2]
ENV = dict(os.environ, PYTHONPATH=str(ROOT))


def qnav_sim(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sim_bridge.cli", *args], capture_output=True, text=True,
                          cwd=cwd, env=ENV, timeout=120)


def test_missing_output_folders_are_created(tmp_path):
    out = qnav_sim(tmp_path, "--map", "paper10", "--can", "virtual:folders", "--speed", "20", "--duration", "0.5",
                   "--log", "run/can.blf", "--trajectory", "run/sub/traj.csv", "-q")
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "run" / "sub" / "traj.csv").is_file()
    assert list(can.LogReader(str(tmp_path / "run" / "can.blf")))  # the sim's frames, readable


def test_uncreatable_folder_is_a_one_line_error_before_the_run(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    out = qnav_sim(tmp_path, "--map", "paper10", "--can", "virtual:folders2", "--speed", "20", "--duration", "0.5",
                   "--log", "file/can.blf")
    assert out.returncode == 2
    errors = [ln for ln in out.stderr.splitlines() if "error" in ln]
    assert len(errors) == 1 and errors[0].startswith("qnav-sim: error: --log file/can.blf: cannot create folder file"), \
        out.stderr
    assert "ticks" not in out.stdout  # refused before any tick ran
