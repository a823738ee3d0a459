"""`qnav bench train`'s code (never its times): one short run writes every figure, each a
positive finite rate measured in that run, with the baseline beside the kernel."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_bench_train_short_run_writes_every_rate(tmp_path):
    out = tmp_path / "bt.json"
    r = subprocess.run([sys.executable, "-m", "ground_station.cli", "bench", "train", "--steps", "200000",
                        "--baseline-seconds", "0.3", "--sector-steps", "20000", "--json", str(out)],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    d = json.loads(out.read_text())
    for key in ("steps_per_s", "baseline_steps_per_s", "ratio", "sector_steps_per_s", "sector_cpu_steps_per_s",
                "sector_memory_grid_moves_per_s"):
        assert math.isfinite(d[key]) and d[key] > 0, (key, d[key])
    assert d["ratio"] == d["steps_per_s"] / d["baseline_steps_per_s"]
    assert d["kernel_steps"] == 200000 and d["baseline_steps"] > 0
    assert "sector-memory moves/s (GridBugTrainer" in r.stdout and "baseline steps/s" in r.stdout
