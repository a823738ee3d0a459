"""The `sector-unmapped` encoding on the twin (ground_station/learn/sector/unmapped.py)
is the robot's reference (firmware_py/unmapped.py): the same unmapped
readings and the same states on many inputs, the bench kernel's rollouts
equal a period-by-period rollout that calls the reference encoder, and the
trainer is seeded and leaves the frozen go rows alone."""

from __future__ import annotations

import math

import numpy as np

from firmware_py import robot_spec
from firmware_py.mapdata import grid_from_rows
from firmware_py.policy import load_policy
from firmware_py.unmapped import DetourMemory, UnmappedSectorEncoder, unmapped_readings
from ground_station.learn.config import TrainConfig
from ground_station.learn.sector.obstacles import sense_obs
from ground_station.learn.sector.twin import bearing_mrad, encode_fast, encoder_arrays, grid_of
from ground_station.learn.sector.unmapped import (
    U_BEST,
    U_DETOUR,
    U_HIT,
    U_LEN,
    U_PREV,
    U_REJOINED,
    U_SIDE,
    U_STALL,
    U_TURN,
    go_rows,
    hand_detour_table,
    note_action_fast,
    unmapped_fast,
    unmapped_params,
    unmapped_state_fast,
)
from ground_station.learn.sector.unmapped_trainer import UnmappedSectorTrainer
from ground_station.maps import load_map
from ground_station.nav.controllers import NavController, policy_table
from ground_station.nav.diagnose import rollout
from ground_station.nav.episodes import run_twin
from ground_station.nav.scenario import episodes

ENC = UnmappedSectorEncoder(block_mm=400, leave_margin_mm=50, switch_ticks=30, rejoin=1)


def _grid(gm):
    return grid_from_rows(["".join("@" if v else "." for v in row) for row in gm.occ], round(gm.cell_size_m * 1000))


def test_unmapped_readings_and_states_equal_the_reference():
    gm = load_map("paper10")
    occ, h, w, c = grid_of(gm)
    grid = _grid(gm)
    rng = np.random.default_rng(3)
    free = gm.free_cells()
    up, dsens, edges = unmapped_params(ENC)
    sectors, sensors, bedges, _ = encoder_arrays(ENC.base)
    which = np.ones(robot_spec.SENSOR_COUNT, dtype=np.bool_)
    ranges = np.zeros(8, dtype=np.int64)
    status = np.zeros(8, dtype=np.int64)
    um = np.zeros(8, dtype=np.int64)
    mem_f = np.zeros(U_LEN, dtype=np.int64)
    mem = DetourMemory()
    n_unmapped = n_detour = 0
    for i in range(3000):
        if i % 40 == 0:
            mem.reset()
            mem_f[:] = 0
        col, row = free[int(rng.integers(len(free)))]
        x = (col + rng.uniform(0.2, 0.8)) * c
        y = (h - row - 1 + rng.uniform(0.2, 0.8)) * c
        th = rng.uniform(-math.pi, math.pi)
        discs = np.array([[x + rng.uniform(-600, 600), y + rng.uniform(-600, 600), rng.uniform(100, 200)]])
        sense_obs(occ, h, w, c, x, y, th, which, ranges, status, discs, np.zeros((0, 5)))
        if i % 7 == 0:  # pose error: the robot's estimate off the true pose
            x += rng.uniform(-120, 120)
            y += rng.uniform(-120, 120)
        xi, yi, ti = math.floor(x + 0.5), math.floor(y + 0.5), math.floor(th * 1000 + 0.5)
        ref = unmapped_readings(grid, xi, yi, ti, list(ranges), list(status), ENC.margin_mm)
        unmapped_fast(occ, h, w, int(c), xi, yi, ti, ranges, status, ENC.margin_mm, um)
        assert list(um) == ref
        n_unmapped += sum(v >= 0 for v in ref)
        gx, gy = x + rng.uniform(-1500, 1500), y + rng.uniform(-1500, 1500)
        b = bearing_mrad(x, y, th, gx, gy)
        d = math.floor(math.hypot(gx - x, gy - y) + 0.5)
        s_ref = ENC.encode(mem, b, d, list(ranges), list(status), ref)
        base = encode_fast(b, ranges, status, sectors, sensors, bedges)
        s_fast = unmapped_state_fast(mem_f, base, b, d, ranges, status, um, up, dsens, edges)
        assert s_fast == s_ref
        assert [bool(mem_f[U_DETOUR]), int(mem_f[U_SIDE]), int(mem_f[U_HIT]), int(mem_f[U_BEST]),
                int(mem_f[U_STALL]), bool(mem_f[U_REJOINED])] == [mem.detour, mem.side, mem.hit_mm, mem.best_mm,
                                                                  mem.stall, mem.rejoined]
        a = int(rng.integers(4))
        mem.note_action(a)
        note_action_fast(mem_f, a)
        assert (mem_f[U_TURN], mem_f[U_PREV]) == (mem.last_turn, mem.prev_turn)
        n_detour += mem.detour
    assert n_unmapped > 300 and n_detour > 100  # both branches were exercised


def test_bench_rollouts_are_the_reference_encoders():
    gm = load_map("rooms-16x16-s1")
    grid = _grid(gm)
    eps = episodes(gm, 8, 2, 3, 1)
    pol = load_policy("policies/sector.qtab")
    q = hand_detour_table(policy_table(pol) * pol.scale, ENC)
    rows = run_twin(eps, {gm.name: gm}, NavController("learnt", ENC, q, "path"))
    for ep, row in zip(eps, rows, strict=True):
        mem = DetourMemory()

        def act(o, mem=mem):
            if not o.memory:  # a new waypoint (rollout clears o.memory): the controller resets per item
                mem.reset()
                o.memory["seen"] = True
            gx, gy = o.ep.waypoints[o.k]
            pose = (math.floor(o.x + 0.5), math.floor(o.y + 0.5), math.floor(o.th * 1000 + 0.5))
            d = math.floor(math.hypot(gx - o.x, gy - o.y) + 0.5)
            s = ENC.encode_on_map(mem, bearing_mrad(o.x, o.y, o.th, gx, gy), d, list(o.ranges), list(o.status),
                                  grid, pose)
            a = int(np.argmax(q[s]))
            mem.note_action(a)
            return a

        ref = rollout(ep, gm, ENC.base, act)
        assert (ref["outcome"], ref["steps"]) == (row["outcome"], round(row["time_s"] / 0.05))
    rows0 = run_twin(eps, {gm.name: gm}, NavController("learnt", ENC, go_rows(policy_table(pol) * pol.scale, ENC),
                                                        "path"))
    detoured = sum(r["outcome"] != r0["outcome"] or r["time_s"] != r0["time_s"] for r, r0 in zip(rows, rows0,
                                                                                                  strict=True))
    assert detoured > 0  # the detour rows changed some episodes


def test_trainer_is_seeded_and_keeps_the_go_rows():
    maps = [load_map("paper10")]
    cfg = TrainConfig(encoding="sector", steps=20000, lr=0.1, seed=4, sector_obstacles=2, sector_movers=1,
                      sector_pool=30, epsilon_start=0.3, epsilon_end=0.05)
    pol = load_policy("policies/sector.qtab")
    q0 = go_rows(policy_table(pol) * pol.scale, ENC)
    out = []
    for _ in range(2):
        q = q0.copy()
        tr = UnmappedSectorTrainer(maps, cfg, ENC)
        tr.stall_steps, tr.stall_cost = 400, 1.0
        tr.run(q, 0, 20000)
        out.append(q)
    assert np.array_equal(out[0], out[1])
    assert np.array_equal(out[0][:ENC.n_go], q0[:ENC.n_go])
    assert np.any(out[0][ENC.n_go:] != 0.0)


def test_cspace_shaping_fields_and_training():
    maps = [load_map("paper10")]
    cfg = TrainConfig(encoding="sector", steps=20000, lr=0.1, seed=5, sector_obstacles=2, sector_movers=0,
                      sector_pool=12, epsilon_start=0.3, epsilon_end=0.05)
    pol = load_policy("policies/sector.qtab")
    q0 = go_rows(policy_table(pol) * pol.scale, ENC)
    tr = UnmappedSectorTrainer(maps, cfg, ENC)
    tr.shape_with_cspace(raster_mm=100.0)
    assert tr.fields.shape == (12, 50, 50)
    for i, ep in enumerate(tr.pool):  # the goal's raster cell is 0, the start's a finite path length
        gx, gy = ep.waypoints[-1]
        assert tr.fields[i, int(gy // 100), int(gx // 100)] == 0.0
        assert np.isfinite(tr.fields[i, int(ep.start[1] // 100), int(ep.start[0] // 100)])
    q = q0.copy()
    tr.run(q, 0, 20000)
    q2 = q0.copy()
    tr2 = UnmappedSectorTrainer(maps, cfg, ENC)
    tr2.run(q2, 0, 20000)
    assert np.array_equal(q[:ENC.n_go], q0[:ENC.n_go]) and not np.array_equal(q, q2)  # the shaping changes learning
