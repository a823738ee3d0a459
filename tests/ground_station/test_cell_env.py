"""CellNavEnv: Gymnasium API conformance, the CellEncoder state layout,
move/collision/goal semantics and seeding through reset only."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import ground_station.learn.envs  # noqa: F401 - registers the ids
from firmware_py import robot_spec
from firmware_py.kinds.cell.encoder import CellEncoder
from ground_station.learn.envs.cell_env import CellNavEnv, cell_transitions, resolve_goals
from ground_station.maps import GridMap, MapError, load_map, parse_map

UP, DOWN, LEFT, RIGHT = (robot_spec.CELL_ACTION_NAMES.index(n) for n in ("up", "down", "left", "right"))


def small_map() -> GridMap:
    occ = parse_map("type octile\nheight 3\nwidth 4\nmap\n....\n.@..\n....\n").occ
    return GridMap("small", occ, {"G": (3, 0), "H": (0, 2)})


def test_check_env_direct_and_registered():
    check_env(CellNavEnv(small_map()), skip_render_check=True)  # render is checked via the registered id
    env = gym.make("qnav/CellNav-v0")
    check_env(env.unwrapped)
    assert env.spec.max_episode_steps == 100


def test_observation_is_the_cell_encoder_index():
    env = CellNavEnv(small_map())
    enc = CellEncoder(4, 3, 2)
    assert env.observation_space.n == enc.n_states
    for goal in (0, 1):
        obs, info = env.reset(seed=0, options={"goal": goal, "start": (2, 1)})
        assert obs == enc.encode(2, 1, goal)
        assert info["cell"] == (2, 1) and info["goal_index"] == goal


def test_moves_follow_the_robot_deltas_north_is_row_minus_one():
    env = CellNavEnv(small_map())
    env.reset(seed=0, options={"goal": 1, "start": (2, 1)})
    _, r, term, trunc, info = env.step(UP)
    assert info["cell"] == (2, 0) and r == pytest.approx(-0.01) and not term and not trunc
    _, _, _, _, info = env.step(RIGHT)
    assert info["cell"] == (3, 0)
    _, _, _, _, info = env.step(DOWN)
    assert info["cell"] == (3, 1)
    _, _, _, _, info = env.step(LEFT)
    assert info["cell"] == (2, 1)


def test_collision_and_goal_terminate_with_their_rewards():
    env = CellNavEnv(small_map(), reward_goal=5.0, reward_collision=-3.0)
    env.reset(seed=0, options={"goal": 0, "start": (2, 1)})
    obs, r, term, _, info = env.step(LEFT)  # into the obstacle at (1, 1)
    assert term and r == -3.0 and info["collision"] and info["cell"] == (2, 1)
    env.reset(seed=0, options={"goal": 0, "start": (3, 1)})
    _, r, term, _, info = env.step(UP)  # onto G at (3, 0)
    assert term and r == 5.0 and info["success"]
    env.reset(seed=0, options={"goal": 0, "start": (0, 0)})
    _, r, term, _, info = env.step(UP)  # off the map
    assert term and info["collision"]


def test_transition_table_matches_the_env():
    gm = load_map("paper10")
    nxt = cell_transitions(gm.occ)
    env = CellNavEnv(gm)
    for c, r in gm.free_cells()[::5]:
        for a in range(4):
            env.reset(options={"goal": 0, "start": (c, r)})
            _, _, _, _, info = env.step(a)
            col, row = info["cell"]
            expected = -1 if info["collision"] else row * gm.width + col
            assert nxt[r * gm.width + c, a] == expected


def test_reset_seeding_is_deterministic_and_covers_goals():
    a, b = CellNavEnv(small_map()), CellNavEnv(small_map())
    seq_a = [a.reset(seed=7)[0]] + [a.reset()[0] for _ in range(50)]
    seq_b = [b.reset(seed=7)[0]] + [b.reset()[0] for _ in range(50)]
    assert seq_a == seq_b
    goals = {o // 12 for o in seq_a}
    assert goals == {0, 1}
    assert all(o % 12 not in (3, 8) for o in seq_a if o // 12 == 0)  # never starts on its goal (3,0)


def test_resolve_goals_names_and_coordinates():
    gm = small_map()
    assert resolve_goals(gm, None) == (["G", "H"], [(3, 0), (0, 2)])
    assert resolve_goals(gm, "H, 2:0") == (["H", "2:0"], [(0, 2), (2, 0)])
    with pytest.raises(MapError, match="no target 'Z'"):
        resolve_goals(gm, "Z")
    with pytest.raises(MapError, match=r"target 1:1 at \(1,1\) is a wall of map"):
        resolve_goals(gm, "1:1")
    with pytest.raises(MapError, match="defines no targets"):
        resolve_goals(GridMap("bare", np.zeros((2, 2), bool)), None)
