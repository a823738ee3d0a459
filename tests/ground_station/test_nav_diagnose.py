"""The navigation diagnosis (ground_station/nav/diagnose.py) and the detour
memory on the bench's twin: a `MemorySectorEncoder` table rolled out by
`nav_eval_mem_kernel` drives exactly as the robot's reference encoder, the
privileged oracle solves the detourable episodes, failures are classified by
what was touched, and the memory trainer is seeded."""

from __future__ import annotations

import math

import numba
import numpy as np

from firmware_py import robot_spec
from firmware_py.encoders import BugMemory, MemorySectorEncoder, SectorEncoder, turn_of
from ground_station.learn.jit import greedy
from ground_station.learn.sector.evaluate import seek_table
from ground_station.learn.sector.kernels import FWD_MM_PER_PERIOD
from ground_station.learn.sector.obstacles import (
    COLLISION,
    LOOP,
    NEAR_MISS_MM,
    SUCCESS,
    TIMEOUT,
    obs_period_step,
    obstacle_clearance_mm,
    sense_obs,
)
from ground_station.learn.sector.twin import bearing_mrad, encode_fast
from ground_station.maps import load_map
from ground_station.nav import diagnose as dg
from ground_station.nav.controllers import NavController
from ground_station.nav.episodes import run_twin
from ground_station.nav.scenario import episodes

MEM = MemorySectorEncoder(15, (0, 1, 7), (100, 400), block_mm=250, leave_margin_mm=100)


def _memory_table() -> np.ndarray:
    """Go rows: the seek table; wall rows: forward unless the front bin is 0
    or 1, then turn away from the followed side (enough to exercise every mode)."""
    base = MEM.base
    q = np.zeros((MEM.n_states, MEM.n_actions))
    r = MEM.range_states
    for t in range(3):
        off = t * MEM.mode_states
        q[off:off + base.n_states] = seek_table(base)
        for mode, away in ((1, 1), (2, 2)):
            for rs in range(r):
                front = rs % base.nbins
                q[off + (MEM.bearing_sectors + mode - 1) * r + rs, away if front < 2 else 0] = 1.0
    return q


def test_memory_rollouts_on_the_twin_are_the_reference_encoders():
    gm = load_map("paper10")
    eps = episodes(gm, 12, 5, 3, 1)
    q = _memory_table()
    rows = run_twin(eps, {gm.name: gm}, NavController("learnt", MEM, q, "path"))

    def reference(o: dg.Obs) -> int:  # the robot's encoder and BugMemory, reset per waypoint
        mem = o.memory.setdefault("bug", BugMemory())
        gx, gy = o.ep.waypoints[o.k]
        b = bearing_mrad(o.x, o.y, o.th, gx, gy)
        d = int(math.floor(math.hypot(gx - o.x, gy - o.y) + 0.5))
        s = MEM.encode(mem, b, d, [int(v) for v in o.ranges], [int(v) for v in o.status])
        a = int(np.argmax(q[s]))
        mem.note_action(a)
        return a

    ref = [dg.rollout(e, gm, MEM.base, reference) for e in eps]
    assert [r["outcome"] for r in rows] == [r["outcome"] for r in ref]
    assert [round(r["time_s"] / (robot_spec.CONTROL_PERIOD_US / 1e6)) for r in rows] == [r["steps"] for r in ref]
    assert turn_of(1) != turn_of(0)  # the previous-turn digit is really in play


def test_oracle_solves_detourable_episodes_and_failures_are_classified():
    gm = load_map("paper10")
    eps = [e for e in episodes(gm, 12, 0, 3, 0) if dg.blocked_segments(e)][:5]
    assert len(eps) == 5
    oracle = dg.Oracle(gm)
    ok = [dg.rollout(e, gm, MEM.base, oracle)["outcome"] == "success" for e in eps]
    assert sum(ok) >= 4, ok
    blind = dg.table_act(seek_table(SectorEncoder(15, (0, 1, 7), (100, 400))))
    rows = [dg.rollout(e, gm, MEM.base, blind) for e in eps]
    assert any(r["outcome"] == "collision" and r["detail"] == "disc" for r in rows)
    assert sum(dg.classify(rows).values()) == len(rows)


def test_memory_obstacle_trainer_is_seeded_and_learns_the_wall_modes():
    from ground_station.learn.config import TrainConfig
    from ground_station.learn.sector.obstacle_trainer import ObstacleSectorTrainer

    cfg = TrainConfig(map="paper10", encoding="sector", steps=60_000, sector_obstacles=3, sector_movers=1,
                      sector_pool=40, seed=2)
    gm = load_map("paper10")
    tables = []
    for _ in range(2):
        tr = ObstacleSectorTrainer([gm], cfg, MEM)
        q = np.zeros((MEM.n_states, MEM.n_actions))
        tr.run(q, 0, 60_000)
        tables.append(q)
    np.testing.assert_array_equal(tables[0], tables[1])
    r = MEM.range_states
    wall_rows = np.concatenate([tables[0][t * MEM.mode_states + MEM.bearing_sectors * r:(t + 1) * MEM.mode_states]
                                for t in range(3)])
    assert np.abs(wall_rows).sum() > 0


def test_hand_bug_table_keeps_the_go_rows_and_follows_the_chosen_side():
    go_enc = SectorEncoder(15, (0, 1, 7), (100, 400))
    go_q = seek_table(go_enc)
    enc = MemorySectorEncoder(15, (0, 1, 2, 6, 7), (100, 400), block_mm=150, leave_margin_mm=100)
    q = dg.hand_bug_table(go_q, go_enc, enc)
    rng = np.random.default_rng(0)
    for _ in range(200):  # go rows: the go table's row for the same bearing and sensors 0, 1, 7
        ranges = [int(v) for v in rng.integers(20, 2000, robot_spec.SENSOR_COUNT)]
        status = [robot_spec.RANGE_VALID] * robot_spec.SENSOR_COUNT
        b = int(rng.integers(-3141, 3141))
        mem = BugMemory()
        mem.side = 1  # a side is chosen but the mode is go: go rows
        s = enc.encode(mem, b, 5000, ranges, status)
        if mem.mode == 0:
            np.testing.assert_array_equal(q[s], go_q[go_enc.encode(b, ranges, status)])
    far = [2000] * robot_spec.SENSOR_COUNT
    st = [robot_spec.RANGE_VALID] * robot_spec.SENSOR_COUNT

    def wall_action(front: int, diag: int, side: int, mode: int = 1, turn: int = 0) -> int:
        r = list(far)
        r[0] = front
        r[7 if mode == 1 else 1], r[6 if mode == 1 else 2] = diag, side
        mem = BugMemory(mode=mode, side=mode, hit_mm=100, last_turn=turn)
        return int(np.argmax(q[enc.encode(mem, 0, 100, r, st)]))

    assert wall_action(300, 300, 300) == 1  # front blocked, wall on the right: turn left (away)
    assert wall_action(1500, 300, 300) == 0  # wall beside in reach: forward along it
    assert wall_action(1500, 1500, 1500) == 2  # wall lost: turn back toward it
    assert wall_action(1500, 1500, 1500, turn=1) == 0  # ... unless it just turned away: forward first
    assert wall_action(1500, 300, 300, mode=2) == 0 and wall_action(300, 300, 300, mode=2) == 2


def test_memory_trainer_keeps_frozen_rows_and_ends_stalled_episodes():
    from ground_station.learn.config import TrainConfig
    from ground_station.learn.sector.obstacle_trainer import ObstacleSectorTrainer

    cfg = TrainConfig(map="paper10", encoding="sector", steps=60_000, sector_obstacles=3, sector_movers=0,
                      sector_pool=40, seed=4)
    gm = load_map("paper10")
    tr = ObstacleSectorTrainer([gm], cfg, MEM)
    frozen = np.zeros(MEM.n_states, dtype=np.bool_)
    frozen[: MEM.bearing_sectors * MEM.range_states] = True  # the go rows after no turn
    tr.frozen = frozen
    q0 = _memory_table()
    q = q0.copy()
    _, succ_plain = tr.run(q, 0, 60_000)
    np.testing.assert_array_equal(q[frozen], q0[frozen])
    assert np.abs(q[~frozen] - q0[~frozen]).sum() > 0
    stalled = ObstacleSectorTrainer([gm], cfg, MEM)
    stalled.frozen = frozen
    stalled.stall_steps, stalled.stall_cost = 40, 1.0
    _, succ_stall = stalled.run(_memory_table(), 0, 60_000)
    assert len(succ_stall) > len(succ_plain)  # stalls end episodes early: more, shorter episodes


@numba.njit
def nav_eval_kernel(q, occ_all, dims, cells, ep_map, ep_start, ep_goal, ep_wp, ep_nwp, ep_rem,
                    ep_discs, ep_nd, ep_movers, ep_nm, sectors, sensors, edges, which, guided,
                    budget_base, budget_factor, stall_steps,
                    out_outcome, out_path, out_steps, out_minclear, out_near):
    """The bench's twin core before the detour memory (moved here from
    ground_station.learn.sector.obstacles as the reference the memory-aware
    kernel is checked against). Greedy rollouts of table q over scenario episodes e (map ep_map[e],
    start pose ep_start[e] = (x, y, th), goal point ep_goal[e], waypoints
    ep_wp[e, :ep_nwp[e]] with remaining lengths ep_rem[e], discs
    ep_discs[e, :ep_nd[e]], movers ep_movers[e, :ep_nm[e]] (copied: the
    scenario arrays stay as given)). guided = 0 steers on the goal alone.
    Outcomes: SUCCESS, COLLISION, LOOP (no new minimum of the guide
    potential for stall_steps periods), TIMEOUT (budget_base + budget_factor
    x planned path length in forward periods). Also: driven length, steps,
    minimum clearance, periods with clearance < NEAR_MISS_MM."""
    ranges = np.zeros(which.shape[0], dtype=np.int64)
    status = np.zeros(which.shape[0], dtype=np.int64)
    rw = np.zeros(7)
    gwp = np.zeros((1, 2))
    grem = np.zeros(1)
    for e in range(ep_map.shape[0]):
        m = ep_map[e]
        h = dims[m, 0]
        w = dims[m, 1]
        c = cells[m]
        occ = occ_all[m]
        discs = ep_discs[e, :ep_nd[e]]
        movers = ep_movers[e, :ep_nm[e]].copy()
        if guided:
            wps = ep_wp[e]
            rem = ep_rem[e]
            nwp = ep_nwp[e]
        else:
            gwp[0, 0] = ep_goal[e, 0]
            gwp[0, 1] = ep_goal[e, 1]
            wps = gwp
            rem = grem
            nwp = 1
        x = ep_start[e, 0]
        y = ep_start[e, 1]
        th = ep_start[e, 2]
        plan_len = ep_rem[e, 0] + math.hypot(x - ep_wp[e, 0, 0], y - ep_wp[e, 0, 1])
        budget = int(budget_base + budget_factor * plan_len / FWD_MM_PER_PERIOD)
        k = 0
        phi = math.hypot(x - wps[0, 0], y - wps[0, 1]) + rem[0]
        best = phi
        since = 0
        path = 0.0
        outcome = TIMEOUT
        minclear = obstacle_clearance_mm(x, y, discs, movers)
        near = 0
        t = 0
        sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, movers)
        s = encode_fast(bearing_mrad(x, y, th, wps[0, 0], wps[0, 1]), ranges, status, sectors, sensors, edges)
        while t < budget:
            a = greedy(q, s)
            x, y, th, phi, _, s, hit, success, driven, k = obs_period_step(
                occ, h, w, c, x, y, th, phi, wps, rem, nwp, k, a, rw, which, ranges, status,
                sectors, sensors, edges, discs, movers, 0.0)
            path += driven
            t += 1
            if hit:
                outcome = COLLISION
                minclear = 0.0
                break
            cl = obstacle_clearance_mm(x, y, discs, movers)
            if cl < minclear:
                minclear = cl
            if cl < NEAR_MISS_MM:
                near += 1
            if success:
                outcome = SUCCESS
                break
            if phi < best - 1.0:
                best = phi
                since = 0
            else:
                since += 1
                if since >= stall_steps:
                    outcome = LOOP
                    break
        out_outcome[e] = outcome
        out_path[e] = path
        out_steps[e] = t
        out_minclear[e] = minclear
        out_near[e] = near


def test_bench_rollouts_of_a_plain_table_are_the_old_kernels():
    """run_twin now calls nav_eval_mem_kernel for every table: with no memory
    it must give nav_eval_kernel's rows exactly (the shipped figures stand)."""
    from firmware_py.policy import load_policy
    from firmware_py.shipped_policies import shipped_policy
    from ground_station.learn.sector.twin import encoder_arrays
    from ground_station.nav.controllers import standard_controllers
    from ground_station.nav.episodes import BUDGET_BASE, BUDGET_FACTOR, OUTCOMES, STALL_STEPS
    from ground_station.nav.scenario import episode_arrays

    gm = load_map("rooms-16x16-s1")
    eps = episodes(gm, 40, 1, 3, 2)
    for ctrl in standard_controllers(load_policy(shipped_policy("sector")), ("learnt", "vfh")):
        ctrl.local = None  # the table alone (the shipped file's local planner runs in nav/planned.py)
        rows = run_twin(eps, {gm.name: gm}, ctrl)
        a = episode_arrays(eps, {gm.name: gm})
        n = len(eps)
        out = (np.zeros(n, dtype=np.int64), np.zeros(n), np.zeros(n, dtype=np.int64), np.zeros(n),
               np.zeros(n, dtype=np.int64))
        nav_eval_kernel(ctrl.q, a["occ"], a["dims"], a["cells"], a["map"], a["start"], a["goal"], a["wp"], a["nwp"],
                        a["rem"], a["discs"], a["nd"], a["movers"], a["nm"], *encoder_arrays(ctrl.encoder), 1,
                        BUDGET_BASE, BUDGET_FACTOR, STALL_STEPS, *out)
        period = robot_spec.CONTROL_PERIOD_US / 1e6
        assert [r["outcome"] for r in rows] == [OUTCOMES[int(v)] for v in out[0]]
        assert [round(r["time_s"] / period) for r in rows] == list(out[2])
        assert [r["min_clearance_mm"] for r in rows] == [round(float(v), 1) for v in out[3]]
        assert [r["near_miss_periods"] for r in rows] == list(out[4])
