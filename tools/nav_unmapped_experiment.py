"""Build, train and judge a `sector-unmapped` policy (docs/training.md, "Readings the map does not explain").

    python tools/nav_unmapped_experiment.py [--init hand|shipped|FILE.npy] [--steps N] [--margin MM]
        [--block MM] [--block-bearing MRAD] [--leave MM] [--stay] [--clear MM] [--switch TICKS] [--rejoin 0|1]
        [--detour-sensors 0,1,2,6,7] [--eps0 E] [--gamma G] [--lr A] [--lr-end B] [--noise MM] [--stall-cost C] [--cspace-shaping]
        [--obstacles K] [--movers M] [--pool N] [--seed S] [--episodes N] [--baselines] [--no-k0]
        [--out FILE.npy] [--qtab FILE]

The table is an `UnmappedSectorEncoder` one (`firmware_py/unmapped.py`, the robot's reference encoder:
the shipped sector state in the go rows, a detour memory entered on range readings the known map does
not explain; the encoder flags default to its defaults). `--init shipped` copies the shipped
`policies/sector.qtab` into the go rows (detour rows zero), `hand` adds the hand-written detour rows
(`learn.sector.unmapped.hand_detour_table`), FILE.npy loads a table. `--steps N` Q-learns the detour
rows (go rows frozen: `UnmappedSectorTrainer`) on a seeded pool over paper10 + the four s0 maps (0..K
discs, 0..M movers per episode), lr A -> B, epsilon E -> 0.05, gamma G, range noise MM, a stall of 400
periods ending a training episode with cost C. Judged (float table) with `nav.episodes.run_twin` on
the bench's own episodes `nav.scenario.episodes(map, N, 0, 3, 2)` and `(map, N, 0, 0, 0)` over the
bench's five maps; `--baselines` also judges the shipped table, seek and vfh on the same episodes;
`--qtab` exports the int8 `.qtab` (with the map) for `qnav bench nav --policy FILE`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from firmware_py.policy import load_policy  # noqa: E402
from firmware_py.unmapped import UnmappedSectorEncoder  # noqa: E402
from ground_station.bench.nav import DEFAULT_MAPS  # noqa: E402
from ground_station.learn.config import TrainConfig  # noqa: E402
from ground_station.learn.export import geometry_of_map, policy_bytes, quantise  # noqa: E402
from ground_station.learn.sector.unmapped import go_rows, hand_detour_table  # noqa: E402
from ground_station.learn.sector.unmapped_trainer import UnmappedSectorTrainer  # noqa: E402
from ground_station.maps import load_map  # noqa: E402
from ground_station.nav.controllers import NavController, policy_table, standard_controllers  # noqa: E402
from ground_station.nav.episodes import run_twin, summarise  # noqa: E402
from ground_station.nav.scenario import episodes  # noqa: E402

TRAIN_MAPS = "paper10,rooms-16x16-s0,trap-16x16-s0,random-16x16-s0,maze-16x16-s0"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--init", default="hand")
    ap.add_argument("--steps", type=int, default=0)
    ap.add_argument("--margin", type=int, default=150)
    ap.add_argument("--block", type=int, default=400)
    ap.add_argument("--block-bearing", type=int, default=785)
    ap.add_argument("--leave", type=int, default=0)
    ap.add_argument("--stay", action="store_true", help="the detour lasts until the next waypoint (no leave rule)")
    ap.add_argument("--clear", type=int, default=0)
    ap.add_argument("--switch", type=int, default=100)
    ap.add_argument("--rejoin", type=int, default=0)
    ap.add_argument("--detour-sensors", default="0,1,2,6,7")
    ap.add_argument("--eps0", type=float, default=0.2)
    ap.add_argument("--gamma", type=float, default=0.95)
    ap.add_argument("--lr", type=float, default=0.1)
    ap.add_argument("--lr-end", type=float, default=0.005)
    ap.add_argument("--noise", type=float, default=10.0, help="range noise std (mm) in training")
    ap.add_argument("--stall-cost", type=float, default=1.0)
    ap.add_argument("--cspace-shaping", action="store_true",
                    help="training pays progress on the configuration-space path length with the discs (privileged)")
    ap.add_argument("--obstacles", type=int, default=3)
    ap.add_argument("--movers", type=int, default=2)
    ap.add_argument("--pool", type=int, default=4000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--episodes", type=int, default=60, help="judging episodes per map (default %(default)s)")
    ap.add_argument("--baselines", action="store_true")
    ap.add_argument("--no-k0", action="store_true", help="skip the no-obstacle judging")
    ap.add_argument("--out", help="save the table (.npy)")
    ap.add_argument("--qtab", help="also export it as a sector-unmapped .qtab (int8, per-state scales)")
    a = ap.parse_args()
    enc = UnmappedSectorEncoder(detour_sensors=tuple(int(v) for v in a.detour_sensors.split(",")),
                                margin_mm=a.margin, block_mm=a.block, block_bearing_mrad=a.block_bearing,
                                leave_margin_mm=a.leave, leave=0 if a.stay else 1, clear_mm=a.clear,
                                switch_ticks=a.switch, rejoin=a.rejoin)
    pol = load_policy("policies/sector.qtab")
    go_q = policy_table(pol) * pol.scale
    if a.init == "hand":
        q = hand_detour_table(go_q, enc)
    elif a.init == "shipped":
        q = go_rows(go_q, enc)
    else:
        q = np.load(a.init)
    if a.steps > 0:
        cfg = TrainConfig(encoding="sector", steps=a.steps, lr=a.lr, sector_lr_end=a.lr_end, gamma=a.gamma,
                          sector_range_noise_mm=a.noise, epsilon_start=a.eps0,
                          epsilon_end=0.05, seed=a.seed, sector_obstacles=a.obstacles, sector_movers=a.movers,
                          sector_pool=a.pool)
        t0 = time.perf_counter()
        tr = UnmappedSectorTrainer([load_map(m) for m in TRAIN_MAPS.split(",")], cfg, enc)
        if a.stall_cost > 0:
            tr.stall_steps, tr.stall_cost = 400, a.stall_cost
        if a.cspace_shaping:
            tr.shape_with_cspace()
            print(f"configuration-space fields for {len(tr.pool)} episodes, {time.perf_counter() - t0:.0f} s",
                  flush=True)
        tr.train(q, a.steps, report=lambda line: print(line, flush=True))
    if a.out:
        np.save(a.out, q)
    if a.qtab:
        data = policy_bytes(quantise(q, "int8", per_state=True), enc, metadata={"guidance": "path", "init": a.init},
                            map_geometry=geometry_of_map("paper10"))
        Path(a.qtab).write_bytes(data)
    ctrls = [NavController("unmapped", enc, q, "path")]
    if a.baselines:
        ctrls += standard_controllers(pol, ("learnt", "seek", "vfh"))
    for k, m in ((3, 2),) if a.no_k0 else ((3, 2), (0, 0)):
        eps = {}
        for spec in DEFAULT_MAPS:
            gm = load_map(spec)
            eps[gm.name] = (gm, episodes(gm, a.episodes, 0, k, m))
        for ctrl in ctrls:
            rows = []
            per = []
            for name, (gm, el) in eps.items():
                r = run_twin(el, {name: gm}, ctrl)
                rows += r
                per.append(f"{name.split('-')[0]} {summarise(r)['success_rate']:.2f}")
            s = summarise(rows)
            print(f"K{k} M{m} {ctrl.name}: success {s['success_rate']:.3f} collision {s['collision_rate']:.3f} "
                  f"{s['outcomes']} ({', '.join(per)})", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
