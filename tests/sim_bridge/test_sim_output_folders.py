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


def test_trajectory_png_says_it_is_the_whole_run_and_names_every_mark(tmp_path, monkeypatch):
    """Issue 30 item 7: the demo's PNG title gave the sim's whole run (189.7 s) beside the summary's
    mission time (82.7 s) without saying so, and its ray fan and robot circle had no legend."""
    import matplotlib

    matplotlib.use("Agg")
    import numpy as np
    from matplotlib.figure import Figure

    from sim_bridge.outputs import write_png
    from sim_bridge.plant import Plant

    saved: list[Figure] = []
    real_savefig = Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda self, *a, **k: (saved.append(self), real_savefig(self, *a, **k))[1])
    plant = Plant(np.zeros((4, 4), dtype=bool))
    for _ in range(3):
        plant.tick_frames()
        plant.step_period()
    write_png(plant, tmp_path / "t.png", {"A": (0.25, 0.25)}, title="m: whole run, 0.2 s of sim time")
    ax = saved[-1].axes[0]
    labels = set(ax.get_legend_handles_labels()[1])
    assert {"trajectory", "start", "robot (end)"} <= labels and any(x.startswith("range ray") for x in labels), labels
    assert ax.get_title() == "m: whole run, 0.2 s of sim time"
