"""Train the sector follower on the local planner's sub-goals and judge it on the bench's episodes.

Trains a table with `ground_station.learn.sector.local_trainer` (every
`LocalFollowerConfig` field is an option: --periods, --lr, --stall-cost, ...),
starting from a float table (default: `build/policies/sector/q.npy`, the
shipped recipe retrained by `qnav train --map paper10 --encoding sector
--steps 20000000 --lr 0.1 --gamma 0.95 --reward-step 0 --epsilon-end 0.05
--seed 0 --out build/policies/sector`), then rolls the greedy table out with
the bench's own loop (`ground_station.nav.planned.rollout`, budget and loop
rule of `qnav bench nav`) on `scenario.episodes(gm, N, seed, K, M)` for the
bench maps (paper10 and the -s1 generated maps), beside the shipped
`policies/sector.qtab` on the SAME episodes, and without obstacles on
paper10 (K0 M0). Writes the table (.npy) and a JSON of the config and
figures. `--eval-only TABLE.npy` skips training.

Example:
    PYTHONPATH=$PWD nice -n 10 .venv/bin/python tools/local_follower_experiment.py \\
        --periods 1000000 --episodes 40 --out build/exp/run1
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from firmware_py.policy import load_policy  # noqa: E402
from ground_station.learn.export import quantise  # noqa: E402
from ground_station.learn.sector.local_trainer import (  # noqa: E402
    BENCH_MAPS,
    LocalFollowerConfig,
    LocalFollowerTrainer,
    follower_encoder,
)
from ground_station.learn.sector.obstacles import COLLISION, LOOP, SUCCESS  # noqa: E402
from ground_station.maps import load_map  # noqa: E402
from ground_station.nav import scenario  # noqa: E402
from ground_station.nav.controllers import NavController, policy_table  # noqa: E402
from ground_station.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS  # noqa: E402
from ground_station.nav.planned import rollout  # noqa: E402

OUT = {SUCCESS: "success", COLLISION: "collision", LOOP: "loop"}


def evaluate(q: np.ndarray, eps_by_map: dict[str, list], maps: dict, cfg_planner) -> dict:
    """Greedy rollouts with the bench loop; per map and overall success / collision rates."""
    from tqdm import tqdm

    ctrl = NavController("learnt", follower_encoder(), np.ascontiguousarray(q, dtype=np.float64), "path", cfg_planner)
    res: dict = {}
    alls: list[str] = []
    total = sum(len(v) for v in eps_by_map.values())
    with tqdm(total=total, unit="ep", leave=False, desc="evaluate") as bar:
        for name, eps in eps_by_map.items():
            outs = []
            for ep in eps:
                o = rollout(ep, maps[name], ctrl, BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS)[0]
                outs.append(OUT.get(o, "timeout"))
                bar.update(1)
            res[name] = _rates(outs)
            res[name]["failures"] = [i for i, o in enumerate(outs) if o != "success"]
            alls += outs
    res["all"] = _rates(alls)
    return res


def keep_confident(q: np.ndarray, q0: np.ndarray, margin: float) -> tuple[np.ndarray, int]:
    """q with the rows of q0 back where q's greedy action differs from q0's by a margin < `margin`."""
    q = q.copy()
    a_new, a_old = q.argmax(1), q0.argmax(1)
    rows = np.nonzero(a_new != a_old)[0]
    weak = [int(s) for s in rows if q[s, a_new[s]] - q[s, a_old[s]] < margin]
    q[weak] = q0[weak]
    return q, len(weak)


def _rates(outs: list[str]) -> dict:
    n = max(1, len(outs))
    return {"episodes": len(outs), "success_rate": outs.count("success") / n,
            "collision_rate": outs.count("collision") / n, "loop_rate": outs.count("loop") / n,
            "timeout_rate": outs.count("timeout") / n}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    for f in dataclasses.fields(LocalFollowerConfig):
        if f.name in ("maps", "planner"):
            continue
        default = f.default
        p.add_argument("--" + f.name.replace("_", "-"), type=type(default), default=default,
                       help=f"LocalFollowerConfig.{f.name} (default {default})")
    p.add_argument("--start", default=str(ROOT / "build/policies/sector/q.npy"), help="float table to start from")
    p.add_argument("--eval-only", default="", help="evaluate this .npy table instead of training")
    p.add_argument("--episodes", type=int, default=40, help="bench episodes per map (3 discs + 2 movers)")
    p.add_argument("--k0-episodes", type=int, default=200, help="paper10 episodes without obstacles")
    p.add_argument("--eval-seed", type=int, default=0, help="seed of the bench episodes (scenario.episodes)")
    p.add_argument("--keep-margin", type=float, default=0.0,
                   help="rows whose greedy action changed from the start table's by less than this margin "
                        "(new value of the new action minus new value of the old one) get the start table's row "
                        "back (0: off)")
    p.add_argument("--int8", action="store_true",
                   help="also roll out the table as the exporter quantises it (int8, one scale per table)")
    p.add_argument("--no-baseline", action="store_true", help="skip the shipped table's rollouts")
    p.add_argument("--out", required=True, help="output prefix: writes PREFIX.npy and PREFIX.json")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    kw = {f.name: getattr(args, f.name) for f in dataclasses.fields(LocalFollowerConfig)
          if f.name not in ("maps", "planner")}
    cfg = LocalFollowerConfig(**kw)
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    report: dict = {"config": cfg.to_json(), "command": " ".join(sys.argv)}
    if args.eval_only:
        q = np.load(args.eval_only).astype(np.float64)
        report["table"] = args.eval_only
    else:
        q = np.load(args.start).astype(np.float64)
        q0 = q.copy()
        t0 = time.time()
        trainer = LocalFollowerTrainer(cfg)
        stats = trainer.run(q)
        report["train"] = stats.summary() | {"wall_s": round(time.time() - t0, 1),
                                             "greedy_changes": int((q.argmax(1) != q0.argmax(1)).sum()),
                                             "greedy_reverse_states": int((q.argmax(1) == 3).sum())}
        np.save(out.with_suffix(".npy"), q)
        print("train", json.dumps(report["train"]), flush=True)
    if args.keep_margin > 0.0:
        q, kept = keep_confident(q, np.load(args.start).astype(np.float64), args.keep_margin)
        report["keep_margin"] = {"margin": args.keep_margin, "rows_restored": kept,
                                 "greedy_changes_left": int((q.argmax(1) != np.load(args.start).argmax(1)).sum())}
        np.save(out.with_name(out.name + "_kept.npy"), q)
        print("keep", json.dumps(report["keep_margin"]), flush=True)
    maps = {n: load_map(n) for n in BENCH_MAPS}
    bench = {n: scenario.episodes(maps[n], args.episodes, args.eval_seed, 3, 2) for n in BENCH_MAPS}
    clear = {"paper10": scenario.episodes(maps["paper10"], args.k0_episodes, args.eval_seed, 0, 0)}
    pc = cfg.planner_config()
    report["scenario"] = {"maps": list(BENCH_MAPS), "episodes_per_map": args.episodes, "seed": args.eval_seed,
                          "discs": 3, "movers": 2, "k0_episodes": args.k0_episodes}
    report["learnt"] = {"bench": evaluate(q, bench, maps, pc), "k0m0": evaluate(q, clear, maps, pc)["all"]}
    if args.int8:
        qt = quantise(q, "int8", per_state=False).table.astype(np.float64)
        report["learnt_int8"] = {"bench": evaluate(qt, bench, maps, pc), "k0m0": evaluate(qt, clear, maps, pc)["all"],
                                 "greedy_changes_vs_float": int((qt.argmax(1) != q.argmax(1)).sum())}
    if not args.no_baseline:
        shipped = policy_table(load_policy(str(ROOT / "policies/sector.qtab")))
        report["shipped"] = {"bench": evaluate(shipped, bench, maps, pc), "k0m0": evaluate(shipped, clear, maps, pc)["all"]}
    out.with_suffix(".json").write_text(json.dumps(report, indent=1))
    print(f"{'map':18} {'learnt succ/coll':>18} {'shipped succ/coll':>18}")
    for name in [*BENCH_MAPS, "all"]:
        le = report["learnt"]["bench"][name]
        sh = report.get("shipped", {}).get("bench", {}).get(name)
        shs = f"{sh['success_rate']:.3f}/{sh['collision_rate']:.3f}" if sh else "-"
        print(f"{name:18} {le['success_rate']:.3f}/{le['collision_rate']:.3f}{'':8} {shs:>18}")
    k0 = report["learnt"]["k0m0"]
    sk0 = report.get("shipped", {}).get("k0m0")
    if args.int8:
        i8 = report["learnt_int8"]
        print(f"int8: bench {i8['bench']['all']['success_rate']:.3f}/{i8['bench']['all']['collision_rate']:.3f}, "
              f"K0 M0 {i8['k0m0']['success_rate']:.3f}, greedy changes {i8['greedy_changes_vs_float']}")
    sk0s = f"{sk0['success_rate']:.3f}/{sk0['collision_rate']:.3f}" if sk0 else "-"
    print(f"{'paper10 K0 M0':18} {k0['success_rate']:.3f}/{k0['collision_rate']:.3f}{'':8} {sk0s:>18}")
    print(f"wrote {out.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
