#!/usr/bin/env python3
"""Regenerate one shipped policy: `python tools/make_policy.py NAME`.

Trains with a fixed seed (`qnav train`, into build/policies/NAME), exports
(`qnav export`) to policies/NAME.qtab and records the export report (policy
id, CRC, rollout figures float vs int) plus the exact commands in
policies/NAME.json, which tests/test_policy_shipped.py checks the file
against. Training is seeded, so the table and the policy id (a CRC of
encoder + table) come out the same on every run; the creation time and the
training wall time in the metadata are the run's own.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shlex
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ground_station.cli import main as qnav  # noqa: E402

POLICIES = {
    "paper10_cell": {
        "train": ["--map", "paper10", "--encoding", "cell", "--targets", "A,B,C,D",
                  "--steps", "3000000", "--seed", "0"],
        "export": ["--dtype", "int8"],
    },
    "sector": {
        # waypoint-guided sector policy (TrainConfig sector_* defaults: guidance path, 15 bearing
        # sectors, sensors 0,1,7, edges 100/400 mm, lr decaying to 0.005); docs/training.md, sector section
        "train": ["--map", "paper10", "--encoding", "sector", "--steps", "20000000", "--lr", "0.1",
                  "--gamma", "0.95", "--reward-step", "0", "--epsilon-end", "0.05", "--seed", "0"],
        # all 44 400 (start, goal, heading) rollouts take ~30 s per table: a seeded sample; the robot
        # re-plans round obstacles its map does not show (firmware_py/kinds/sector/, default parameters)
        "export": ["--dtype", "int8", "--sample", "8000", "--seed", "0", "--local-planner"],
    },
    "sector_memory": {
        # sector-memory (cell-stepped Bug memory), direct setting (no waypoints): the recipe is the CLI
        # default for the encoding (its kind's recipe, ground_station/learn/kinds.py); docs/training.md, sector-memory
        "train": ["--map", "paper10", "--encoding", "sector-memory", "--seed", "0"],
        # every (start, goal, heading) of paper10 (44 400 grid rollouts take well under a second)
        "export": ["--dtype", "int8"],
    },
}


def make(name: str) -> dict:
    spec = POLICIES[name]
    run_dir = ROOT / "build" / "policies" / name
    out = ROOT / "policies" / f"{name}.qtab"
    train = ["train", *spec["train"], "--out", str(run_dir), "--quiet"]
    export = ["export", str(run_dir), *spec["export"], "--out", str(out)]
    if qnav(train) != 0:
        raise SystemExit(f"qnav {shlex.join(train)} failed")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = qnav(export)
    if rc != 0:
        raise SystemExit(f"qnav {shlex.join(export)} failed")
    report = json.loads(buf.getvalue())
    report["out"] = str(out.relative_to(ROOT))
    rel = str(run_dir.relative_to(ROOT))
    report["commands"] = [shlex.join(["qnav", *train]).replace(str(run_dir), rel),
                          shlex.join(["qnav", *export]).replace(str(run_dir), rel).replace(str(out), report["out"])]
    (ROOT / "policies" / f"{name}.json").write_text(json.dumps(report, indent=1, sort_keys=True) + "\n")
    return report


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("names", nargs="+", choices=sorted(POLICIES), metavar="NAME",
                   help=f"policy to regenerate: {', '.join(sorted(POLICIES))}")
    args = p.parse_args()
    for name in args.names:
        r = make(name)
        print(f"{r['out']}: {r['bytes']} bytes id={r['policy_id']} success float={r['success_rate']['float']} "
              f"int={r['success_rate']['int']} path_ratio_mean float={r['path_ratio_mean']['float']} "
              f"int={r['path_ratio_mean']['int']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
