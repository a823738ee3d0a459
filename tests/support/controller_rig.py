"""Helpers for the controller tests: small real policies (written and read back
through the .qtab writer/loader) and an ideal kinematic plant that turns wheel
speeds into encoder counts, for driving the pure controller core."""

from __future__ import annotations

import math
from array import array
from collections import deque

from firmware_py import robot_spec
from firmware_py.control.controller import Controller
from firmware_py.control.io import Inputs
from firmware_py.policy import MapGeometry, Policy, dump_policy, load_policy

TICKS_PER_MM = robot_spec.ENCODER_TICKS_PER_REV / (2 * math.pi * robot_spec.WHEEL_RADIUS_MM)
FORWARD, TURN_LEFT, TURN_RIGHT, REVERSE = range(4)
UP, DOWN, LEFT, RIGHT = range(4)
SECTOR_TRAINING_MAP = MapGeometry(500, 10, 10)  # what the hand-made sector policies record (paper10's)


def sector_seek_policy(policy_id: int = 1) -> Policy:
    """A hand-made sector policy: go forward when the goal is ahead, else turn
    towards it (no obstacle avoidance)."""
    from firmware_py.kinds.sector.encoder import (
        SectorEncoder,  # a kind's package only when asked for
    )

    enc = SectorEncoder()
    per_bearing = enc.nbins ** len(enc.sensors)
    vals = array("b")
    half = enc.bearing_sectors // 2
    for s in range(enc.n_states):
        b = s // per_bearing
        a = FORWARD if b == 0 else TURN_LEFT if b <= half else TURN_RIGHT
        vals.extend(100 if i == a else 0 for i in range(enc.n_actions))
    return load_policy(dump_policy(enc, vals, "int8", 0.01, policy_id=policy_id, map_geometry=SECTOR_TRAINING_MAP))


def bfs(lines: list[str], goal: tuple[int, int]) -> dict[tuple[int, int], int]:
    h, w = len(lines), len(lines[0])
    dist = {goal: 0}
    q = deque([goal])
    while q:
        c, r = q.popleft()
        for dc, dr in robot_spec.CELL_ACTION_DELTAS:
            n = (c + dc, r + dr)
            if 0 <= n[0] < w and 0 <= n[1] < h and lines[n[1]][n[0]] == "." and n not in dist:
                dist[n] = dist[(c, r)] + 1
                q.append(n)
    return dist


def cell_bfs_policy(lines: list[str], goals: list[tuple[int, int]], cell_mm: int = 500,
                    policy_id: int = 2) -> Policy:
    """An optimal cell policy from BFS: Q = -(steps to the goal after the move)."""
    from firmware_py.kinds.cell.encoder import CellEncoder  # a kind's package only when asked for

    h, w = len(lines), len(lines[0])
    enc = CellEncoder(w, h, len(goals))
    vals = array("b", [-127] * (enc.n_states * enc.n_actions))
    for gi, goal in enumerate(goals):
        dist = bfs(lines, goal)
        for (c, r) in dist:
            s = enc.encode(c, r, gi)
            for a, (dc, dr) in enumerate(robot_spec.CELL_ACTION_DELTAS):
                n = (c + dc, r + dr)
                if n in dist:
                    vals[s * enc.n_actions + a] = max(-126, -dist[n])
    return load_policy(dump_policy(enc, vals, "int8", 0.1, goals=goals, cell_mm=cell_mm,
                                   policy_id=policy_id))


class Kinematic:
    """Ideal differential drive: wheel speeds in, pose and encoder counts out."""

    def __init__(self, x_mm: float, y_mm: float, heading_rad: float) -> None:
        self.x, self.y, self.th = x_mm, y_mm, heading_rad
        self.left_mm = self.right_mm = 0.0

    def step(self, left: float, right: float, dt_s: float) -> None:
        n = 10
        for _ in range(n):
            dl, dr = left * dt_s / n, right * dt_s / n
            ds, dth = (dl + dr) / 2, (dr - dl) / robot_spec.WHEEL_BASE_MM
            self.x += ds * math.cos(self.th + dth / 2)
            self.y += ds * math.sin(self.th + dth / 2)
            self.th += dth
            self.left_mm += dl
            self.right_mm += dr

    def counts(self) -> tuple[int, int]:
        return round(self.left_mm * TICKS_PER_MM), round(self.right_mm * TICKS_PER_MM)


def fresh_inputs(plant: Kinematic, t_us: int, ranges_mm: int = robot_spec.RANGE_MAX_MM) -> Inputs:
    inp = Inputs()
    inp.ranges_mm = [ranges_mm] * robot_spec.SENSOR_COUNT
    inp.range_status = [robot_spec.RANGE_TOO_FAR if ranges_mm >= robot_spec.RANGE_MAX_MM else robot_spec.RANGE_VALID] * robot_spec.SENSOR_COUNT
    inp.ranges_us = [t_us, t_us]
    inp.enc_left, inp.enc_right = plant.counts()
    inp.enc_us = t_us
    inp.bumper_us = t_us
    inp.driver_us = t_us
    inp.driver_state = 1
    return inp


class Rig:
    """Controller + kinematic plant, stepped at the control period."""

    def __init__(self, ctrl: Controller, plant: Kinematic, t0_us: int = 0) -> None:
        self.ctrl, self.plant, self.t = ctrl, plant, t0_us
        self.commands: list = []
        self.inp = Inputs()  # nothing received yet

    def tick(self, fresh: bool = True, **overrides) -> object:
        if fresh:
            self.inp = fresh_inputs(self.plant, self.t)
        for k, v in overrides.items():
            setattr(self.inp, k, v)
        out = self.ctrl.step(self.inp, self.t)
        self.commands.append(out.motor)
        if out.motor is not None:
            self.last_motor = out.motor
            self.plant.step(out.motor.left_mm_s, out.motor.right_mm_s, robot_spec.CONTROL_PERIOD_US / 1e6)
        self.t += robot_spec.CONTROL_PERIOD_US
        return out

    def run_until(self, pred, max_ticks: int = 2000, **overrides) -> int:
        for i in range(max_ticks):
            self.tick(**overrides)
            if pred():
                return i + 1
        raise AssertionError(f"condition not met in {max_ticks} ticks; state {self.ctrl.state.name}")
