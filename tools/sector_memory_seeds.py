"""Seed study of the sector-memory (cell-stepped Bug memory) recipe: train
`--seeds` seeds of `RECIPES["sector-memory"]` (with `--set FIELD=VALUE`
overrides), evaluate each greedily on every (start, goal, heading) of the
maps, and print per map the mean success with its bootstrapped 95 % CI over
the seeds (`ground_station.learn.study.bootstrap_ci`), the worst seed, the
collisions, and the hand-written table (`hand_table`) on the same episodes;
then how many seeds meet the acceptance (paper10 >= 0.95, every other map
>= 0.90, no collision). docs/training.md, sector-memory section.

    PYTHONPATH=. python tools/sector_memory_seeds.py --seeds 20 [--set grid_wall_cost=0] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from ground_station.learn.config import recipe_config  # noqa: E402
from ground_station.learn.sector.gridbug_train import (  # noqa: E402
    GridBugTrainer,
    evaluate_gridbug,
    gridbug_encoder,
    hand_table,
)
from ground_station.learn.study import bootstrap_ci  # noqa: E402
from ground_station.maps import load_map  # noqa: E402

MAPS = "paper10,rooms-16x16-s1,trap-16x16-s1,maze-16x16-s1,rooms-16x16-s2,trap-16x16-s2,maze-16x16-s2"


def _value(text: str) -> object:
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--maps", default=MAPS, help="comma-separated evaluation maps (default %(default)s)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="TrainConfig override")
    p.add_argument("--json", metavar="FILE", help="also write every seed's figures as JSON")
    a = p.parse_args()
    over = {k: _value(v) for k, v in (s.split("=", 1) for s in a.set)}
    names = [m for m in a.maps.split(",") if m]
    gms = {m: load_map(m) for m in names}
    succ = np.zeros((len(names), a.seeds))
    coll = np.zeros((len(names), a.seeds), dtype=np.int64)
    enc = gridbug_encoder(recipe_config("sector-memory", over))
    for seed in range(a.seeds):
        cfg = recipe_config("sector-memory", {**over, "seed": seed})
        maps = [load_map(cfg.map)] + [load_map(m) for m in cfg.sector_maps.split(",") if m]
        q = np.zeros((enc.n_states, enc.n_actions))
        GridBugTrainer(maps, cfg, enc).run(q, 0, cfg.steps)
        for i, m in enumerate(names):
            r = evaluate_gridbug(q, gms[m], enc)
            succ[i, seed], coll[i, seed] = r["success_rate"], r["collisions"]
        print(f"seed {seed}: " + " ".join(f"{succ[i, seed]:.4f}" for i in range(len(names))), flush=True)
    hand = {m: evaluate_gridbug(hand_table(enc), gms[m], enc) for m in names}
    print(f"\nrecipe sector-memory {over or ''}, {a.seeds} seeds; success over every (start, goal, heading)")
    print("| map | episodes | learnt mean [95 % CI] | worst seed | seeds >= target | collisions (all seeds) "
          "| hand-written |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    ok = np.ones(a.seeds, dtype=bool)
    for i, m in enumerate(names):
        mean, lo, hi = bootstrap_ci(succ[i])
        target = 0.95 if m == "paper10" else 0.90
        meets = (succ[i] >= target) & (coll[i] == 0)
        ok &= meets
        print(f"| {m} | {hand[m]['episodes']} | {mean:.3f} [{lo:.3f}, {hi:.3f}] | {succ[i].min():.3f} | "
              f"{int(meets.sum())}/{a.seeds} | {int(coll[i].sum())} | {hand[m]['success_rate']:.3f} |")
    print(f"\nseeds meeting every target: {int(ok.sum())}/{a.seeds} ({', '.join(str(s) for s in np.flatnonzero(ok))})")
    if a.json:
        Path(a.json).write_text(json.dumps({"overrides": over, "maps": names, "success": succ.tolist(),
                                            "collisions": coll.tolist(),
                                            "hand": {m: hand[m]["success_rate"] for m in names}}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
