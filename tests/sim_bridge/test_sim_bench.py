"""`qnav bench sim` runs end to end and reports every figure (no timing asserted)."""

from __future__ import annotations

import json
import subprocess
import sys

# the `qnav` console script's entry point (`python -m ground_station.cli` would load
# the CLI module twice, so its CliError would not be the one commands raise)
QNAV = [sys.executable, "-c", "import sys; from ground_station.cli import main; sys.exit(main())"]


def test_bench_sim_smoke(tmp_path):
    out = subprocess.run([*QNAV, "bench", "sim",
                          "--sim-seconds", "1", "--ticks", "40", "--json", str(tmp_path / "b.json")],
                         capture_output=True, text=True, timeout=100)
    assert out.returncode == 0, out.stderr
    assert "lockstep_ticks_per_s_remote" in out.stdout
    result = json.loads((tmp_path / "b.json").read_text())
    for key in ("rtf", "lockstep_ticks_per_s_inprocess", "lockstep_ticks_per_s_remote",
                "remote_vs_inprocess", "physics_steps_per_s"):
        assert result[key] > 0, key
    assert result["missed_ticks"] == 0
    assert result["details"]["inprocess"]["ticks"] == 40 == result["details"]["remote"]["ticks"]


def test_bench_sim_rejects_bad_arguments():
    out = subprocess.run([*QNAV, "bench", "sim", "--ticks", "0"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "must be positive" in out.stderr
