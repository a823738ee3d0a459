"""A policy kind that exists only in the tests, on both sides of the registry: the robot's
`PolicyKind` (firmware_py.kinds: its encoder section and its decisions) and the station's
`TrainingKind` (ground_station.learn.kinds: its options, trainer and evaluation).

`toy-spin` has two states, the way ahead is clear (0) or closer than `near_mm` (1), and two
actions, forward and turn left in place. Its trainer is a real, tiny Q-learning loop on the
two-state task "drive when clear, turn when blocked", so a table trained with a sensible
config drives, and one trained with `lr` too small to learn does not.
"""

from __future__ import annotations

import random
import struct
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from firmware_py import kinds as robot_kinds
from firmware_py.kinds.base import Decision, DriveTick, KindDriver, PolicyKind, Unpacked
from ground_station.learn.kinds import TrainingKind, option

NAME = "toy-spin"
CODE = 200
ACTIONS = ((120, 120), (-90, 90))  # forward, turn left in place (mm/s)
_SECTION = struct.Struct("<H")


@dataclass(frozen=True)
class SpinEncoder:
    near_mm: int = 300
    kind: str = field(default=NAME, init=False)

    @property
    def n_states(self) -> int:
        return 2

    @property
    def n_actions(self) -> int:
        return len(ACTIONS)

    def to_dict(self) -> dict[str, object]:
        return asdict(self)


# --- the robot's half ------------------------------------------------------------------

def _unpack(sec: bytes, n_actions: int, _sensors: int) -> Unpacked:
    if len(sec) != _SECTION.size + 4 * n_actions:
        raise ValueError(f"toy-spin section is {len(sec)} bytes")
    return Unpacked(SpinEncoder(_SECTION.unpack_from(sec, 0)[0]), actions_at=_SECTION.size)


class SpinDriver(KindDriver):
    def step(self, tick: DriveTick) -> Decision:
        s = int(tick.ranges_mm[0] < self.policy.encoder.near_mm)
        a = self.policy.best_action(s)
        return Decision(ACTIONS[a], self.decided(s, a))


ROBOT_KIND = PolicyKind(name=NAME, code=CODE, actions=ACTIONS, unpack=_unpack,
                        pack=lambda enc, _goals, _cell: _SECTION.pack(enc.near_mm), driver=SpinDriver)


def drive(pol):  # type: ignore[no-untyped-def]
    """Arm a controller running `pol`, give it a goal ahead and tick with the way clear, then
    blocked: [(wheels, status)] after each of the two ticks."""
    from firmware_py.control.controller import Controller
    from firmware_py.vehicle import CtrlState, VehicleConfig
    from tests.support.controller_rig import Kinematic, Rig

    ctrl = Controller(VehicleConfig(), pol, start_pose_mm=(250, 250, 0), localise=False)
    rig = Rig(ctrl, Kinematic(250, 250, 0.0))
    rig.tick()
    assert ctrl.arm() == (True, "") and ctrl.go_to(4750, 250) == (True, "")
    seen = []
    for ranges in ([2000] * 8, [200] * 8):  # clear, then something close ahead
        rig.tick(ranges_mm=ranges)
        assert ctrl.state == CtrlState.DRIVING
        seen.append(((rig.last_motor.left_mm_s, rig.last_motor.right_mm_s), ctrl.status()))
    return seen


# --- the station's half ----------------------------------------------------------------

@dataclass
class SpinOptions:
    near_mm: int = option(300, "a range reading ahead below this (mm) is 'blocked'")
    turn_reward: float = option(1.0, "reward for turning when blocked")


def train(cfg, gridmap, progress: bool = False):  # type: ignore[no-untyped-def]
    """Epsilon-greedy one-step Q-learning on the two-state task (each step a fresh state)."""
    from ground_station.learn.train import TrainResult, initial_table

    enc = SpinEncoder(cfg.options.near_mm)
    q = initial_table(cfg, enc.n_states, enc.n_actions)
    rng = random.Random(cfg.seed)
    returns, successes = [], []
    t0 = time.perf_counter()
    for _ in range(cfg.steps):
        s = rng.randrange(2)
        a = rng.randrange(2) if rng.random() < cfg.epsilon_end else int(np.argmax(q[s]))
        good = a == s  # clear -> forward (0), blocked -> turn (1)
        r = (cfg.reward_goal if s == 0 else cfg.options.turn_reward) if good else cfg.reward_collision
        q[s, a] += cfg.lr * (r - q[s, a])
        returns.append(r)
        successes.append(good)
    return TrainResult(q, np.array(returns), np.array(successes, dtype=bool), {"encoder": enc.to_dict()},
                       time.perf_counter() - t0)


def evaluate(q, run, gridmap, *, sample=None, seed: int = 0, full: bool = False) -> dict:  # type: ignore[no-untyped-def]
    right = [int(np.argmax(q[s])) == s for s in range(2)]
    return {"success_rate": float(np.mean(right)), "episodes": 2, "path_ratio_mean": 1.0 if all(right) else None}


STATION_KIND = TrainingKind(
    name=NAME, summary="clear or blocked ahead (a test's toy)", options=SpinOptions, prefix="toy_",
    train=train, evaluate=evaluate, encoder_from_dict=lambda d: SpinEncoder(int(d["near_mm"])))


def unregister_robot_kind(name: str) -> None:
    """Forget a kind the test registered with the robot's registry (firmware_py.kinds); a shipped
    one is imported again when next asked for."""
    kind = robot_kinds._BY_NAME.pop(name, None)
    if kind is not None:
        robot_kinds._BY_CODE.pop(kind.code, None)
