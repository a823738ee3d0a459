"""The in-process lockstep rig: the pymunk plant and the robot's controller on
a real python-can `virtual` bus, one control tick at a time.

The real pieces: `sim_bridge.plant.Plant` (its `tick_frames` / `handle` /
`step_period`, the same stepping `qnav-sim --lockstep` runs) in the calling
thread, and `firmware_py.control.node.RobotNode` + `Controller` on the sim
clock in their own threads, with `firmware_py.control.goals.GoalRunner`
arming and starting the goals as `qnav-robot --goal` does.

`LockstepRig.tick()` sends one tick's frames and waits for its answer (the
MotorCommand carrying counter k). Hooks for tests and fault scenarios: a
`frames_hook` may mangle or drop the plant's frames, `deliver=False`
withholds the answer from the motor driver, `before_answer` runs before it
is delivered, `send()` puts frames of other nodes on the bus, and the
vehicle can be called between ticks. Answers to other ticks are counted
(`repeated_answers`, `stale_answers`) and offered to the driver, which must
ignore them too.

`run_episode` drives one whole episode on the rig (what `qnav bench hil`,
the HIL tests and the guidance tests use). `sim_bridge.plant.run_lockstep`
is the bus-facing loop for a controller in another process; it stays in
sim_bridge, which does not import the ground station.
"""

from __future__ import annotations

import math
import random
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can

from firmware_py import can_protocol as cp
from firmware_py import robot_spec
from firmware_py.clock import SimClock
from firmware_py.control.controller import Controller
from firmware_py.control.goals import GoalRunner
from firmware_py.control.localiser import LocaliserConfig
from firmware_py.control.node import RobotNode
from firmware_py.policy import Policy, load_policy
from firmware_py.shipped_policies import shipped_policy
from firmware_py.vehicle import CtrlState, VehicleConfig
from sim_bridge.profiles import PlantProfile

CELL_POLICY = shipped_policy("paper10_cell")
PERIOD_US = robot_spec.CONTROL_PERIOD_US

SENSOR_FRAMES = frozenset({"RangeSectors0", "RangeSectors1", "EncoderCounts", "Bumper"})

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
    import numpy as np

    from ground_station.maps import bfs_distances  # the station's one shortest-path module

    targets = list(policy.goals)
    while True:
        goal = rng.choice(targets)
        dist = bfs_distances(gm.occ, *goal)  # [row, col], -1 unreachable
        cells = sorted((int(c), int(r)) for r, c in zip(*np.nonzero(dist >= min_cells), strict=True))
        if cells:
            break
    col, row = rng.choice(cells)
    x, y = robot_spec.cell_center_mm(col, row, gm.height, policy.cell_mm)
    heading = rng.uniform(-math.pi, math.pi)
    return (x / 1000, y / 1000, heading), robot_spec.cell_center_mm(*goal, gm.height, policy.cell_mm)


class _TimedController(Controller):
    """The controller, with the CPU time of every `step` recorded (thread CPU
    time: what the tick costs, not what the shared machine's scheduler adds)."""

    def __init__(self, *args, **kw) -> None:
        super().__init__(*args, **kw)
        self.step_cpu_ns: list[int] = []

    def step(self, inputs, now_us, tick=None):  # type: ignore[no-untyped-def]
        t0 = time.thread_time_ns()
        out = super().step(inputs, now_us, tick)
        self.step_cpu_ns.append(time.thread_time_ns() - t0)
        return out


class LockstepRig:
    """See the module docstring. Use as a context manager; `start` is
    (x_m, y_m, heading_rad), `goals_mm` the goal or mission for the GoalRunner
    (none: the vehicle is left to the caller)."""

    def __init__(self, occ, policy: Policy | None, start: tuple[float, float, float],
                 goals_mm: list[tuple[int, int]], *, seed: int = 0,
                 vehicle: VehicleConfig | None = None, answer_timeout_s: float = 5.0,
                 profile: PlantProfile | None = None, localise: bool = True, robot: Any = None,
                 robot_map: bool = True) -> None:
        from dataclasses import replace

        from firmware_py.drives import open_drive
        from sim_bridge.plant import Plant, SimConfig
        from sim_bridge.world import Pose

        channel = f"faults-{uuid.uuid4().hex}"
        self.sim_bus = can.Bus(interface="virtual", channel=channel)
        self.node_bus = can.Bus(interface="virtual", channel=channel)
        config = SimConfig(seed=seed) if profile is None else SimConfig.from_profile(profile, seed=seed)
        config = replace(config, robot=robot)  # robot: a firmware_py.profile.RobotProfile (its drive backend)
        self.plant = Plant(occ, config, Pose(*start))
        self.ctrl = _TimedController(vehicle or VehicleConfig(), policy, lockstep=True, localise=localise,
                               localiser_config=LocaliserConfig(seed=seed), profile=robot,
                               start_pose_mm=(round(start[0] * 1000), round(start[1] * 1000),
                                              round(start[2] * 1000)))
        if robot_map:  # the map the plant simulates is the robot's own (issue 32), as `qnav map upload` makes it
            from firmware_py.mapdata import OccupancyGrid

            cell_mm = round(config.cell_size_m * 1000)
            grid = OccupancyGrid(cell_mm, occ.shape[1], occ.shape[0], bytes(int(v != 0) for v in occ.flat))
            # (ok, why): a cell policy for another map refuses it, naming both, and keeps its own
            self.robot_map_result = self.ctrl.set_robot_map(grid) if self.ctrl.cfg.cell_size_mm == cell_mm else (
                False, f"sim cells {cell_mm} mm, robot {self.ctrl.cfg.cell_size_mm} mm")
        drive = open_drive(robot) if robot is not None else None
        self.node = RobotNode(self.node_bus, self.ctrl, SimClock(), lockstep=True, drive=drive)
        # the tick's answer: qnav's MotorCommand carries the counter, other drives end with a SimTickAck
        self._answer = ("MotorCommand", "Cmd_Counter") if drive is None or drive.answers_lockstep else (
            "SimTickAck", "Ack_Counter")
        self.runner = GoalRunner(self.ctrl, goals_mm)
        if goals_mm:
            self.node.after_tick.append(self.runner)
        self.answer_timeout_s = answer_timeout_s
        self.commands: list[tuple[int, int, int, int]] = []  # (t_us, left, right, counter) of each answer
        self.states: list[tuple[int, CtrlState]] = []  # state after each tick
        self.stale_answers = 0  # answers to ticks other than the current and the previous one
        self.repeated_answers = 0  # the previous tick's answer again (a duplicated SimTick)
        self._last_counter: int | None = None
        self.answers_withheld = 0
        # (t_us, true x, y mm, believed x, y mm, odometry x, y mm) after each tick
        self.poses: list[tuple[int, float, float, int, int, int, int]] = []

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
            if msg.arbitration_id != cp.FRAME_IDS[self._answer[0]]:
                plant.handle(msg, lockstep=True)
                continue
            _, sig = cp.decode(msg)
            if sig[self._answer[1]] != want:
                if sig[self._answer[1]] == self._last_counter:
                    self.repeated_answers += 1
                else:
                    self.stale_answers += 1
                plant.handle(msg, lockstep=True)  # the driver must ignore it too
                continue
            answer = msg
        if before_answer is not None:
            before_answer()
        if deliver:
            plant.handle(answer, lockstep=True)
        else:
            self.answers_withheld += 1
        _, sig = cp.decode(answer)
        left, right = ((sig["Cmd_LeftSpeed"], sig["Cmd_RightSpeed"]) if "Cmd_LeftSpeed" in sig
                       else (round(plant.motors.target[0]), round(plant.motors.target[1])))
        self.commands.append((plant.time_us, left, right, want))
        self._last_counter = want
        self.states.append((plant.time_us, self.ctrl.state))
        st = self.ctrl.status()
        true = plant.world.pose
        self.poses.append((plant.time_us, true.x * 1000, true.y * 1000, st.x_mm, st.y_mm, st.odom_x_mm, st.odom_y_mm))
        plant.step_period()
        return left, right

    def run_until(self, t_us: int, **kw) -> None:
        """Tick until sim time `t_us`; `kw` as for `tick()`."""
        while self.plant.time_us < t_us:
            self.tick(**kw)

    def first_transition_to(self, state: CtrlState, after_us: int = -1):
        for tr in self.ctrl.transitions:
            if tr.dst == state and tr.t_us >= after_us:
                return tr
        return None


# --- whole episodes ---------------------------------------------------------------

@dataclass
class Episode:
    result: str  # "reached", "FAULT: ...", "stopped: ...", "timeout", "goal refused: ..."
    contacts: int  # wall contact events in the plant
    sim_s: float
    wall_s: float
    ticks: int
    final_error_mm: float  # ground truth distance to the goal at the end
    commands: list[tuple[int, int, int, int]] = field(default_factory=list)  # (t_us, left, right, counter)
    transitions: list[tuple[int, str, str, str]] = field(default_factory=list)
    latency_us: list[float] = field(default_factory=list)
    step_cpu_us: list[float] = field(default_factory=list)  # Controller.step thread CPU time per tick
    belief_error_mm: float = 0.0  # |true - believed position| at the end
    odom_error_mm: float = 0.0  # |true - dead-reckoning position| at the end
    belief_error_max_mm: float = 0.0  # largest |true - believed| while driving
    poses: list[tuple[int, float, float, int, int, int, int]] = field(default_factory=list)  # LockstepRig.poses

    @property
    def success(self) -> bool:
        return self.result == "reached" and self.contacts == 0


def cut_sensors_after(t_us: int) -> FramesHook:
    """A frames hook that drops every sensor frame from sim time `t_us` on."""
    def hook(_tick: int, now_us: int, frames: list[can.Message]) -> list[can.Message]:
        if now_us < t_us:
            return frames
        return [m for m in frames if cp.frame_name(m.arbitration_id) not in SENSOR_FRAMES]
    return hook


def run_episode(occ, policy: Policy | None, start: tuple[float, float, float],
                goals_mm: list[tuple[int, int]], *, max_sim_s: float = 120.0, seed: int = 0,
                vehicle: VehicleConfig | None = None, frames_hook: FramesHook | None = None,
                before_tick: Callable[[LockstepRig], None] | None = None,
                stop_when_done: bool = True, answer_timeout_s: float = 5.0,
                profile: PlantProfile | None = None, localise: bool = True, robot: Any = None) -> Episode:
    """Drive one lockstep episode on a `LockstepRig` until the GoalRunner is done
    (unless `stop_when_done` is False) or `max_sim_s` of sim time.

    `before_tick(rig)` runs before every tick (e.g. to send an EStop);
    `frames_hook` as for `LockstepRig.tick`."""
    end_us = round(max_sim_s * 1e6)
    t0 = time.perf_counter()
    with LockstepRig(occ, policy, start, goals_mm, seed=seed, vehicle=vehicle,
                     answer_timeout_s=answer_timeout_s, profile=profile, localise=localise, robot=robot) as rig:
        while rig.plant.time_us < end_us:
            if stop_when_done and rig.runner.done.is_set():
                break
            if before_tick is not None:
                before_tick(rig)
            rig.tick(frames_hook=frames_hook)
    wall = time.perf_counter() - t0
    plant, runner = rig.plant, rig.runner
    pose = plant.world.pose
    err = math.inf
    if goals_mm:
        gx, gy = goals_mm[-1]
        err = math.hypot(pose.x * 1000 - gx, pose.y * 1000 - gy)
    result = runner.result if runner.done.is_set() else "timeout"
    errs = [math.hypot(p[1] - p[3], p[2] - p[4]) for p in rig.poses] or [0.0]
    last = rig.poses[-1] if rig.poses else (0, 0.0, 0.0, 0, 0, 0, 0)
    return Episode(belief_error_mm=errs[-1], odom_error_mm=math.hypot(last[1] - last[5], last[2] - last[6]),
                   belief_error_max_mm=max(errs), poses=rig.poses,
                   step_cpu_us=[v / 1000 for v in rig.ctrl.step_cpu_ns],
                   result=result, contacts=plant.world.contact_events, sim_s=plant.time_us / 1e6,
                   wall_s=wall, ticks=plant.tick, final_error_mm=err, commands=rig.commands,
                   transitions=[(t.t_us, t.src.name, t.dst.name, t.cause) for t in rig.ctrl.transitions],
                   latency_us=[v / 1000 for v in rig.node.latency_ns])
