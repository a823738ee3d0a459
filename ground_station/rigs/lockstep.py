"""A lockstep HIL rig for fault injection: pymunk plant + RobotNode/Controller
on a real python-can `virtual` bus, with hooks on both directions.

Like `ground_station.bench.hil.run_episode`, but stepped one control tick at
a time by the caller, so a scenario can mangle the plant's frames
(`frames_hook`), withhold the controller's answers from the motor driver
(`deliver=False`), send frames of other nodes and call the vehicle between
ticks. The answer to tick k is the MotorCommand carrying counter k; other
MotorCommands (answers to replayed ticks) are counted in `stale_answers`.
"""

from __future__ import annotations

import math
import random
import time
import uuid
from collections import deque
from collections.abc import Callable

import can

from firmware_py import can_protocol as cp
from firmware_py import robot_spec
from firmware_py.clock import SimClock
from firmware_py.control.controller import Controller
from firmware_py.control.goals import GoalRunner
from firmware_py.control.node import RobotNode
from firmware_py.policy import Policy, load_policy
from firmware_py.shipped_policies import shipped_policy
from firmware_py.vehicle import CtrlState, VehicleConfig

CELL_POLICY = shipped_policy("paper10_cell")
PERIOD_US = robot_spec.CONTROL_PERIOD_US

FramesHook = Callable[[int, int, list[can.Message]], list[can.Message]]  # (tick, t_us, frames)


def paper10():
    from ground_station.maps import load_map

    return load_map("paper10")


def cell_policy() -> Policy:
    return load_policy(CELL_POLICY)


def far_trip(gm, policy: Policy, rng: random.Random, min_cells: int = 6):
    """A seeded (start (x_m, y_m, heading_rad), goal_mm) at least `min_cells`
    BFS steps from one of the policy's targets, so the robot is still driving
    seconds after it starts."""
    targets = list(policy.goals)
    while True:
        goal = rng.choice(targets)
        dist = _bfs(gm.occ, goal)
        cells = sorted(c for c, d in dist.items() if d >= min_cells)
        if cells:
            break
    col, row = rng.choice(cells)
    x, y = robot_spec.cell_center_mm(col, row, gm.height, policy.cell_mm)
    heading = rng.uniform(-math.pi, math.pi)
    return (x / 1000, y / 1000, heading), robot_spec.cell_center_mm(*goal, gm.height, policy.cell_mm)


def _bfs(occ, goal: tuple[int, int]) -> dict[tuple[int, int], int]:
    """4-connected steps from every free cell to `goal` (plain Python: no jit warm-up)."""
    h, w = occ.shape
    dist = {goal: 0}
    queue = deque([goal])
    while queue:
        c, r = queue.popleft()
        for dc, dr in robot_spec.CELL_ACTION_DELTAS:
            n = (c + dc, r + dr)
            if 0 <= n[0] < w and 0 <= n[1] < h and not occ[n[1]][n[0]] and n not in dist:
                dist[n] = dist[(c, r)] + 1
                queue.append(n)
    return dist


class LockstepRig:
    """See the module docstring. Use as a context manager."""

    def __init__(self, occ, policy: Policy | None, start: tuple[float, float, float],
                 goals_mm: list[tuple[int, int]], *, seed: int = 0,
                 vehicle: VehicleConfig | None = None, answer_timeout_s: float = 5.0) -> None:
        from sim_bridge.plant import Plant, SimConfig
        from sim_bridge.world import Pose

        channel = f"faults-{uuid.uuid4().hex}"
        self.sim_bus = can.Bus(interface="virtual", channel=channel)
        self.node_bus = can.Bus(interface="virtual", channel=channel)
        self.plant = Plant(occ, SimConfig(seed=seed), Pose(*start))
        self.ctrl = Controller(vehicle or VehicleConfig(), policy, lockstep=True,
                               start_pose_mm=(round(start[0] * 1000), round(start[1] * 1000),
                                              round(start[2] * 1000)))
        self.node = RobotNode(self.node_bus, self.ctrl, SimClock(), lockstep=True)
        self.runner = GoalRunner(self.ctrl, goals_mm)
        if goals_mm:
            self.node.after_tick.append(self.runner)
        self.answer_timeout_s = answer_timeout_s
        self.commands: list[tuple[int, int, int]] = []  # (t_us, left, right) of each tick's answer
        self.states: list[tuple[int, CtrlState]] = []  # state after each tick
        self.stale_answers = 0  # answers to ticks other than the current and the previous one
        self.repeated_answers = 0  # the previous tick's answer again (a duplicated SimTick)
        self._last_counter: int | None = None
        self.answers_withheld = 0

    def __enter__(self) -> LockstepRig:
        self.node.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.node.stop()
        self.sim_bus.shutdown()
        self.node_bus.shutdown()

    @property
    def time_us(self) -> int:
        return self.plant.time_us

    def send(self, frame: can.Message) -> None:
        """A frame from another node (the sim side of the bus)."""
        self.sim_bus.send(frame)

    def tick(self, frames_hook: FramesHook | None = None, deliver: bool = True,
             before_answer: Callable[[], None] | None = None) -> tuple[int, int]:
        """One lockstep tick; returns the answer's (left, right) wheel speeds."""
        plant = self.plant
        frames = plant.tick_frames()
        if frames_hook is not None:
            frames = frames_hook(plant.tick, plant.time_us, frames)
        for f in frames:
            self.sim_bus.send(f)
        want = plant.tick % cp.TICK_MODULUS
        deadline = time.perf_counter() + self.answer_timeout_s
        answer = None
        while answer is None:
            msg = self.sim_bus.recv(timeout=max(0.0, deadline - time.perf_counter()))
            if msg is None:
                raise RuntimeError(f"controller did not answer SimTick {plant.tick}")
            if msg.arbitration_id != cp.MOTOR_COMMAND_ID:
                plant.handle(msg, lockstep=True)
                continue
            _, sig = cp.decode(msg)
            if sig["Cmd_Counter"] != want:
                if sig["Cmd_Counter"] == self._last_counter:
                    self.repeated_answers += 1
                else:
                    self.stale_answers += 1
                plant.handle(msg, lockstep=True)  # the driver must ignore it too
                continue
            answer = msg
        if before_answer is not None:
            before_answer()
        _, sig = cp.decode(answer)
        self.commands.append((plant.time_us, sig["Cmd_LeftSpeed"], sig["Cmd_RightSpeed"]))
        if deliver:
            plant.handle(answer, lockstep=True)
        else:
            self.answers_withheld += 1
        self._last_counter = want
        self.states.append((plant.time_us, self.ctrl.state))
        plant.step_period()
        return sig["Cmd_LeftSpeed"], sig["Cmd_RightSpeed"]

    def run_until(self, t_us: int, **kw) -> None:
        while self.plant.time_us < t_us:
            self.tick(**kw)

    def state_at(self, t_us: int) -> CtrlState | None:
        for t, s in self.states:
            if t == t_us:
                return s
        return None

    def first_transition_to(self, state: CtrlState, after_us: int = -1):
        for tr in self.ctrl.transitions:
            if tr.dst == state and tr.t_us >= after_us:
                return tr
        return None
