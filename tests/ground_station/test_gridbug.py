"""The cell-stepped sector-memory encoding on the ground station: the jitted
encoder equals the reference, the occupancy flags are what the sensors
read, the hand-written table completes paper10, training is deterministic and
chunkable, the CLI path (train / eval / export) and the robot's controller
driving a kinematic plant with the twin's range readings."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from firmware_py import robot_spec
from firmware_py.control.controller import Controller
from firmware_py.kinds.sector_memory.gridbug import GridBugEncoder, GridBugMemory
from firmware_py.policy import load_policy
from firmware_py.vehicle import CtrlState, VehicleConfig
from ground_station.learn.config import TrainConfig, validate_config
from ground_station.learn.export import policy_bytes, quantise
from ground_station.learn.sector.twin import DEFAULT_TW, disc_hits, grid_of, sense
from ground_station.learn.sector_memory import kernels as gb
from ground_station.learn.sector_memory.trainer import (
    GridBugTrainer,
    encoder_params,
    evaluate_gridbug,
    gridbug_encoder,
    hand_table,
)
from ground_station.maps import load_map
from tests.support.controller_rig import Kinematic, Rig

BENCH_MAPS = ["paper10", "rooms-16x16-s1", "trap-16x16-s1", "maze-16x16-s1"]


@pytest.mark.parametrize("enc", [GridBugEncoder(), GridBugEncoder(leave_margin_mm=300, wall_bearing=True)])
def test_jitted_state_equals_the_reference(enc):
    rng = np.random.default_rng(1)
    params = encoder_params(enc)
    for _ in range(200):  # sequences: the memory carries over between decisions
        ref = GridBugMemory()
        ref.reset(int(rng.integers(4)))
        mem = np.array([ref.mode, ref.side, ref.hit_mm, ref.heading], dtype=np.int64)
        for _ in range(30):
            dx, dy = (int(v) for v in rng.integers(-6, 7, 2) * 500 + rng.integers(-260, 261, 2))
            free = int(rng.integers(16))
            s_ref = enc.encode_free(ref, dx, dy, free)
            s_jit = gb.gb_state(mem, dx, dy, free, params)
            assert s_jit == s_ref
            assert list(mem) == [ref.mode, ref.side, ref.hit_mm, ref.heading]
            move = int(rng.integers(4))
            ref.note_move(move)
            mem[3] = (mem[3] + move) % 4


@pytest.mark.parametrize("name", BENCH_MAPS)
def test_occupancy_flags_are_what_the_sensors_read(name):
    """At every free cell centre facing each grid direction, the reference
    encoder's flags from the twin's range readings equal the occupancy grid's."""
    gm = load_map(name)
    occ, h, w, c = grid_of(gm)
    enc = GridBugEncoder()
    which = np.ones(robot_spec.SENSOR_COUNT, dtype=np.bool_)
    ranges = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
    status = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
    closest_free, farthest_blocked = 10**9, 0
    for col, row in gm.free_cells():
        x, y = (col + 0.5) * c, (h - row - 0.5) * c
        want = gb.free_world(occ, h, w, col, row)
        for d in range(4):
            sense(occ, h, w, c, x, y, d * math.pi / 2, which, ranges, status, DEFAULT_TW)
            r, st = [int(v) for v in ranges], [int(v) for v in status]
            assert enc.free_mask(d, 0, r, st) == want, (name, col, row, d)
            valid = st[0] == robot_spec.RANGE_VALID
            if want >> d & 1 and valid:
                closest_free = min(closest_free, r[0])
            elif valid:
                farthest_blocked = max(farthest_blocked, r[0])
    assert farthest_blocked <= 110 and closest_free >= 590  # the geometry behind free_mm = 350


def test_hand_table_completes_paper10_without_collisions():
    enc = GridBugEncoder()
    rep = evaluate_gridbug(hand_table(enc), load_map("paper10"), enc)
    assert rep["episodes"] == 75 * 74 * 8 and rep["success_rate"] == 1.0 and rep["collisions"] == 0


def test_a_move_into_a_wall_is_a_collision_in_evaluation():
    enc = GridBugEncoder()
    q = np.zeros((enc.n_states, 4))  # always forward
    rep = evaluate_gridbug(q, load_map("paper10"), enc, sample=300)
    assert rep["collisions"] > 0 and rep["collisions"] + rep["timeouts"] + round(rep["success_rate"] * 300) == 300


def test_trainer_deterministic_and_chunkable():
    cfg = TrainConfig.of(encoding="sector-memory", steps=60_000, lr=0.1, seed=4, grid_wall_cost=0.02)
    enc = gridbug_encoder(cfg)
    maps = [load_map("paper10")]
    q1 = np.zeros((enc.n_states, 4))
    r1, s1 = GridBugTrainer(maps, cfg, enc).run(q1, 0, cfg.steps)
    q2 = np.zeros((enc.n_states, 4))
    tr = GridBugTrainer(maps, cfg, enc)
    parts = [tr.run(q2, 0, 25_000), tr.run(q2, 25_000, 35_000)]
    assert np.array_equal(q1, q2)
    assert np.array_equal(r1, np.concatenate([p[0] for p in parts]))
    assert np.array_equal(s1, np.concatenate([p[1] for p in parts]))
    assert len(r1) > 100 and np.abs(q1).max() > 0


def test_config_validation():
    with pytest.raises(ValueError, match="free_mm"):
        validate_config(TrainConfig.of(encoding="sector-memory", grid_free_mm=10))
    with pytest.raises(ValueError, match="grid_wall_bearing"):
        validate_config(TrainConfig.of(encoding="sector-memory", grid_wall_bearing=2))
    with pytest.raises(ValueError, match="training: q"):
        validate_config(TrainConfig.of(encoding="sector-memory", learner="sarsa"))


def _qnav(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ground_station.cli", *args], capture_output=True, text=True,
                          timeout=600)


def test_cli_train_eval_export(tmp_path):
    run = tmp_path / "run"
    p = _qnav("train", "--encoding", "sector-memory", "--map", "paper10", "--steps", "200000", "--seed", "1",
              "--out", str(run))
    assert p.returncode == 0, p.stderr
    meta = json.loads((run / "meta.json").read_text())
    assert meta["encoding"] == "sector-memory" and meta["guidance"] == "direct"
    assert meta["config"]["grid_wall_cost"] == 0.02  # the recipe's default
    p = _qnav("eval", str(run), "--map", "maze-16x16-s1", "--sample", "200", "--json")
    assert p.returncode == 0, p.stderr
    rep = json.loads(p.stdout)
    assert rep["encoding"] == "sector-memory" and rep["episodes"] == 200 and 0 <= rep["success_rate"] <= 1
    # the hand-written Bug rule in the same state, on the same 200 episodes, beside it
    base = rep["baseline"]
    assert base["episodes"] == 200 and base["success_rate"] == 1.0 and base["collisions"] == 0
    p = _qnav("export", str(run), "--out", str(tmp_path / "p.qtab"), "--sample", "200")
    assert p.returncode == 0, p.stderr
    exp = json.loads(p.stdout)
    assert set(exp["success_rate"]) == {"float", "int"}
    assert load_policy(str(tmp_path / "p.qtab")).kind == "sector-memory"
    p = _qnav("train", "--encoding", "sector-memory", "--grid-free-mm", "5", "--out", str(tmp_path / "x"))
    assert p.returncode != 0 and "free_mm" in p.stderr and "Traceback" not in p.stderr


def test_bench_hil_refuses_waypoints_for_a_sector_memory_policy():
    p = _qnav("bench", "hil", "--only", "sector", "--sector-policy", "policies:sector_memory", "--pairs", "1")
    assert p.returncode != 0 and "use --guidance direct" in p.stderr


def _drive(pol, gm, start: tuple[int, int], heading: float, goal: tuple[int, int], max_ticks: int = 6000):
    """The controller on an ideal kinematic plant, ranges from the twin at the true pose."""
    occ, h, w, c = grid_of(gm)
    x0, y0 = robot_spec.cell_center_mm(*start, h, int(c))
    gx, gy = robot_spec.cell_center_mm(*goal, h, int(c))
    ctrl = Controller(VehicleConfig(), pol, start_pose_mm=(x0, y0, round(heading * 1000)), localise=False)
    plant = Kinematic(x0, y0, heading)
    rig = Rig(ctrl, plant)
    which = np.ones(robot_spec.SENSOR_COUNT, dtype=np.bool_)
    ranges = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
    status = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)

    def readings() -> dict:
        sense(occ, h, w, c, plant.x, plant.y, plant.th, which, ranges, status, DEFAULT_TW)
        return {"ranges_mm": [int(v) for v in ranges], "range_status": [int(v) for v in status]}

    rig.tick(**readings())
    assert ctrl.arm() == (True, "")
    assert ctrl.go_to(gx, gy) == (True, "")
    for _ in range(max_ticks):
        rig.tick(**readings())
        assert not disc_hits(occ, h, w, c, plant.x, plant.y, float(robot_spec.ROBOT_RADIUS_MM)), "wall contact"
        if ctrl.state != CtrlState.DRIVING:
            break
    return ctrl


def test_controller_drives_the_hand_table_round_a_wall_on_the_twin():
    """paper10: starts whose straight way is blocked (the robot must follow a
    wall), random headings; the controller encodes, takes the greedy move and
    the primitive drives it, reaching every goal without touching a wall."""
    gm = load_map("paper10")
    enc = GridBugEncoder()
    qt = quantise(hand_table(enc), "int8")
    occ, h, w, c = grid_of(gm)
    pol = load_policy(policy_bytes(qt, enc, map_geometry=(500, gm.width, gm.height)))
    rng = np.random.default_rng(3)
    free = gm.free_cells()
    walls = 0
    for _ in range(4):
        i, j = rng.choice(len(free), 2, replace=False)
        ctrl = _drive(pol, gm, free[i], float(rng.uniform(-math.pi, math.pi)), free[j])
        assert ctrl.state == CtrlState.GOAL_REACHED, ctrl.transitions[-1].cause
        walls += ctrl.driver.memory.side != 0
    assert walls > 0  # at least one of them needed the wall modes


def test_controller_waits_for_valid_axis_readings_then_counts_a_dropout_as_blocked():
    """A dropout (INVALID) on an axis sensor at a decision: the robot stands
    still and reads again; after GRID_INVALID_RETRY_TICKS it decides with the
    reading counted as blocked (never drives into what it did not see)."""
    from firmware_py.kinds.sector_memory import GRID_INVALID_RETRY_TICKS

    gm = load_map("paper10")
    enc = GridBugEncoder()
    pol = load_policy(policy_bytes(quantise(hand_table(enc), "int8"), enc, map_geometry=(500, gm.width, gm.height)))
    occ, h, w, c = grid_of(gm)
    start, goal = (0, 0), (4, 0)  # open row: the hand table goes straight east
    x0, y0 = robot_spec.cell_center_mm(*start, h, int(c))
    ctrl = Controller(VehicleConfig(), pol, start_pose_mm=(x0, y0, 0), localise=False)
    plant = Kinematic(x0, y0, 0.0)
    rig = Rig(ctrl, plant)
    which = np.ones(robot_spec.SENSOR_COUNT, dtype=np.bool_)
    ranges = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)
    status = np.zeros(robot_spec.SENSOR_COUNT, dtype=np.int64)

    def readings(dropout: bool) -> dict:
        sense(occ, h, w, c, plant.x, plant.y, plant.th, which, ranges, status, DEFAULT_TW)
        st = [int(v) for v in status]
        if dropout:
            st[0] = robot_spec.RANGE_INVALID  # ahead (east): the way to the goal
        return {"ranges_mm": [int(v) for v in ranges], "range_status": st}

    rig.tick(**readings(False))
    assert ctrl.arm() == (True, "") and ctrl.go_to(*robot_spec.cell_center_mm(*goal, h, int(c))) == (True, "")
    for _ in range(GRID_INVALID_RETRY_TICKS):
        rig.tick(**readings(True))
        assert ctrl._state_index == -1 and (rig.last_motor.left_mm_s, rig.last_motor.right_mm_s) == (0, 0)
    rig.tick(**readings(True))  # out of patience: decides with ahead blocked, so it does not go east
    assert ctrl._state_index >= 0 and ctrl._action != 0 and ctrl.driver.memory.mode != 0
    # with valid readings from the start the same decision is forward (east, goal-ward, free)
    ctrl2 = Controller(VehicleConfig(), pol, start_pose_mm=(x0, y0, 0), localise=False)
    plant2 = Kinematic(x0, y0, 0.0)
    rig2 = Rig(ctrl2, plant2)
    rig2.tick(**readings(False))
    assert ctrl2.arm() == (True, "") and ctrl2.go_to(*robot_spec.cell_center_mm(*goal, h, int(c))) == (True, "")
    rig2.tick(**readings(False))
    assert ctrl2._action == 0 and ctrl2.driver.memory.mode == 0
