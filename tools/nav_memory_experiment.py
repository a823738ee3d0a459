"""Train and judge a detour-memory sector policy with unmapped obstacles (the docs/training.md experiments).

    python tools/nav_memory_experiment.py [--steps N] [--sensors 0,1,7] [--edges 100,400] [--block MM]
        [--leave MM] [--init shipped|hand-bug|FILE.npy|zero] [--eps0 E] [--gamma G] [--step-reward R]
        [--obstacles K] [--movers M] [--pool N] [--seed S] [--episodes N] [--out FILE.npy] [--qtab FILE]

The policy is a `MemorySectorEncoder` table (the robot's reference encoder: Bug mode + side held per
waypoint + previous turn; the controller resets the memory per mission item) trained by
`ObstacleSectorTrainer` on a scenario pool over paper10 and the four s0 generated maps (0..K discs,
0..M movers per episode), lr 0.1 -> 0.005, epsilon E -> 0.05; `--init shipped` copies the shipped sector
table into the go rows (its encoder must be the base: sensors a superset of 0,1,7 with the same edges),
`hand-bug` additionally writes the hand-written wall rows (`nav.diagnose.hand_bug_table`, needs sensors
0,1,2,6,7). `--steps 0` only judges the initial table. Judged with `nav.episodes.run_twin` on
`nav.scenario.episodes(map, N, 0, 3, 2)` and `(map, N, 0, 0, 0)` over the bench's five maps.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from firmware_py.encoders import MemorySectorEncoder  # noqa: E402
from firmware_py.policy import load_policy  # noqa: E402
from ground_station.bench.nav import DEFAULT_MAPS  # noqa: E402
from ground_station.learn.config import TrainConfig  # noqa: E402
from ground_station.learn.export import geometry_of_map, policy_bytes, quantise  # noqa: E402
from ground_station.learn.sector.obstacle_trainer import ObstacleSectorTrainer  # noqa: E402
from ground_station.maps import load_map  # noqa: E402
from ground_station.nav.controllers import NavController, policy_table  # noqa: E402
from ground_station.nav.diagnose import go_rows_table, hand_bug_table  # noqa: E402
from ground_station.nav.episodes import run_twin, summarise  # noqa: E402
from ground_station.nav.scenario import episodes  # noqa: E402

TRAIN_MAPS = "paper10,rooms-16x16-s0,trap-16x16-s0,random-16x16-s0,maze-16x16-s0"


def initial_table(init: str, enc: MemorySectorEncoder) -> np.ndarray:
    if init == "zero":
        return np.zeros((enc.n_states, enc.n_actions))
    if init not in ("shipped", "hand-bug"):
        return np.load(init)
    pol = load_policy("policies/sector.qtab")
    go_q = policy_table(pol) * pol.scale
    if init == "shipped":  # go rows only; the wall rows start at zero
        return go_rows_table(go_q, pol.encoder, enc)  # type: ignore[arg-type]
    return hand_bug_table(go_q, pol.encoder, enc)  # type: ignore[arg-type]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=10_000_000)
    ap.add_argument("--sensors", default="0,1,2,6,7")
    ap.add_argument("--edges", default="100,400")
    ap.add_argument("--block", type=int, default=150)
    ap.add_argument("--leave", type=int, default=100)
    ap.add_argument("--init", default="zero")
    ap.add_argument("--eps0", type=float, default=1.0)
    ap.add_argument("--gamma", type=float, default=0.95)
    ap.add_argument("--step-reward", type=float, default=0.0)
    ap.add_argument("--obstacles", type=int, default=3)
    ap.add_argument("--movers", type=int, default=2)
    ap.add_argument("--pool", type=int, default=4000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--episodes", type=int, default=60, help="judging episodes per map (default %(default)s)")
    ap.add_argument("--freeze-go", action="store_true", help="learn the wall rows only (go rows stay as initialised)")
    ap.add_argument("--stall-cost", type=float, default=0.0,
                    help="> 0: end a training episode that stalls for 400 periods (the bench's loop rule) with this cost")
    ap.add_argument("--out", help="save the table (.npy)")
    ap.add_argument("--qtab", help="also export it as a sector-memory .qtab (int8, per-state scales) for "
                                   "`qnav bench nav --policy FILE`")
    a = ap.parse_args()
    enc = MemorySectorEncoder(15, tuple(int(v) for v in a.sensors.split(",")),
                              tuple(int(v) for v in a.edges.split(",")), block_mm=a.block, leave_margin_mm=a.leave)
    q = initial_table(a.init, enc)
    if a.steps > 0:
        cfg = TrainConfig(encoding="sector", steps=a.steps, lr=0.1, gamma=a.gamma, reward_step=a.step_reward,
                          epsilon_start=a.eps0, epsilon_end=0.05, seed=a.seed, sector_obstacles=a.obstacles,
                          sector_movers=a.movers, sector_pool=a.pool)
        tr = ObstacleSectorTrainer([load_map(m) for m in TRAIN_MAPS.split(",")], cfg, enc)
        if a.stall_cost > 0:
            tr.stall_steps, tr.stall_cost = 400, a.stall_cost
        if a.freeze_go:
            go = np.zeros(enc.n_states, dtype=np.bool_)
            for t in range(3):
                go[t * enc.mode_states:t * enc.mode_states + enc.bearing_sectors * enc.range_states] = True
            tr.frozen = go
        tr.train(q, a.steps, report=lambda line: print(line, flush=True))
    if a.out:
        np.save(a.out, q)
    if a.qtab:
        data = policy_bytes(quantise(q, "int8", per_state=True), enc, metadata={"guidance": "path", "init": a.init},
                            map_geometry=geometry_of_map("paper10"))
        Path(a.qtab).write_bytes(data)
    ctrl = NavController("learnt", enc, q, "path")
    for k, m in ((3, 2), (0, 0)):
        rows = []
        for spec in DEFAULT_MAPS:
            gm = load_map(spec)
            rows += run_twin(episodes(gm, a.episodes, 0, k, m), {gm.name: gm}, ctrl)
        s = summarise(rows)
        print(f"K{k} M{m}: success {s['success_rate']:.3f} collision {s['collision_rate']:.3f} {s['outcomes']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
