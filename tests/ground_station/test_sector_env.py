"""SectorNavEnv: Gymnasium contract, determinism, and agreement with the twin."""

import math

import gymnasium as gym
import numpy as np
from gymnasium.utils.env_checker import check_env

import ground_station.learn.envs  # noqa: F401  (registers the ids)
from firmware_py import robot_spec
from firmware_py.kinds.sector.encoder import SectorEncoder
from ground_station.learn.envs.sector_env import SectorNavEnv
from ground_station.maps import load_map


def test_check_env_passes():
    check_env(SectorNavEnv("paper10"), skip_render_check=True)
    check_env(gym.make("qnav/SectorNav-v0").unwrapped, skip_render_check=True)


def test_same_seed_same_episode_and_seeding_only_through_reset():
    def roll(seed):
        env = SectorNavEnv("paper10")
        obs, info = env.reset(seed=seed)
        out = [(obs, info["x_mm"], info["y_mm"], info["heading_rad"], info["goal"])]
        acts = np.random.default_rng(99).integers(0, 4, size=200)
        for a in acts:
            obs, r, term, trunc, info = env.step(int(a))
            out.append((obs, r, info["x_mm"], info["y_mm"]))
            if term:
                break
        return out

    assert roll(5) == roll(5)
    assert roll(5) != roll(6)


def test_state_is_the_reference_encoding_of_the_readings():
    enc = SectorEncoder()
    env = SectorNavEnv("paper10", encoder=enc)
    rng = np.random.default_rng(0)
    obs, info = env.reset(seed=1)
    for _ in range(300):
        x, y, th = info["x_mm"], info["y_mm"], info["heading_rad"]
        gx, gy = info["waypoints"][info["waypoint"]]  # the bearing is to the current waypoint
        bearing = int(math.floor((math.atan2(gy - y, gx - x) - th + math.pi) % (2 * math.pi) * 1000
                                 - math.pi * 1000 + 0.5))
        ranges = [0] * robot_spec.SENSOR_COUNT
        status = [robot_spec.RANGE_VALID] * robot_spec.SENSOR_COUNT
        for k, s in enumerate(enc.sensors):
            ranges[s] = int(info["ranges_mm"][k])
            status[s] = int(info["status"][k])
        assert obs == enc.encode(bearing, ranges, status)
        obs, _, term, _, info = env.step(int(rng.integers(0, 3)))
        if term:
            obs, info = env.reset()


def test_turning_in_place_from_a_cell_centre_never_collides_and_forward_into_a_wall_does():
    env = SectorNavEnv("paper10")
    gm = load_map("paper10")
    # cell (0, 2) west of the obstacle (1, 2); heading east
    env.reset(seed=0, options={"start": (0, 2), "heading": 0.0, "goal": (0, 9)})
    for _ in range(200):
        _, _, term, _, info = env.step(1)
        assert not term
    env.reset(seed=0, options={"start": (0, 2), "heading": 0.0, "goal": (0, 9)})
    for _ in range(200):
        _, r, term, _, info = env.step(0)
        if term:
            break
    assert term and info["collision"] and not info["success"]
    assert r == -env.reward.collision
    assert gm.occ[2, 1]


def test_driving_straight_to_the_goal_succeeds_with_positive_progress():
    env = SectorNavEnv("paper10")
    # (0, 9) -> (0, 6): straight north along the free west column
    obs, info = env.reset(seed=0, options={"start": (0, 9), "heading": math.pi / 2, "goal": (0, 6)})
    total = 0.0
    for _ in range(200):
        obs, r, term, _, info = env.step(0)
        total += r
        if term:
            break
    assert info["success"] and not info["collision"]
    assert math.isclose(info["y_mm"], robot_spec.cell_center_mm(0, 6, 10)[1], abs_tol=robot_spec.GOAL_TOLERANCE_MM)
    assert total > 0
