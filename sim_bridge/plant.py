"""The CAN-facing plant: the robot's boards and the sim clock on one bus.

`Plant` is the core, free of I/O: `tick_frames()` samples every sensor at the current sim time and
returns the frames of one control tick (SimTick last), `handle(msg)` applies a received frame,
`step_period()` advances physics by one control period in fixed `robot_spec.PHYSICS_DT_US` steps.
`run_lockstep` and `run_paced` are the thin shells that move frames over a python-can bus; the
lockstep handshake is specified in docs/can-protocol.md.

The robot it plays is one robot profile (`SimConfig.robot`, a `firmware_py.profile.RobotProfile`;
None is the built-in robot, `profile.DEFAULT`): the world's body radius and wheel base, the
encoders' wheel and counts per turn, the boards' gear ratio and signs, and the range sensors'
angles, order, count and range all come from it (docs/robot-profile.md, "The sim plays the
profile").

Outputs: CAN log through python-can's `can.Logger` (sim-time stamps), the ground-truth trajectory
CSV and a PNG (see `sim_bridge.outputs`).
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import can
import numpy as np

from firmware_py import can_protocol as cp
from firmware_py import robot_spec
from firmware_py.profile import DEFAULT as DEFAULT_ROBOT
from sim_bridge.battery import Battery
from sim_bridge.motors import MotorDriver, MotorParams
from sim_bridge.profiles import PlantProfile
from sim_bridge.sensors import RangeParams, RangeSensors, WheelEncoders, bumper_signals
from sim_bridge.world import BodyParams, Pose, World

STEPS_PER_TICK = robot_spec.CONTROL_PERIOD_US // robot_spec.PHYSICS_DT_US
BATTERY_EVERY_TICKS = robot_spec.CONTROL_RATE_HZ // 2  # BatteryStatus at 2 Hz
TRAJECTORY_FIELDS = ("t_s", "tick", "x_m", "y_m", "heading_rad", "wheel_left_mm_s",
                     "wheel_right_mm_s", "cmd_left_mm_s", "cmd_right_mm_s", "bumper")


class LockstepError(RuntimeError):
    """The lockstep handshake could not start (no controller answered)."""


@dataclass
class SimConfig:
    seed: int = 0
    cell_size_m: float = robot_spec.DEFAULT_CELL_SIZE_MM / 1000
    ranges: RangeParams = field(default_factory=RangeParams)
    motors: MotorParams = field(default_factory=MotorParams)
    body: BodyParams = field(default_factory=BodyParams)
    encoder_slip_std: float = 0.0
    encoder_scale: tuple[float, float] = (1.0, 1.0)  # (left, right) measured / true travel
    # the robot profile the sim plays: its geometry, sensors and boards (firmware_py.profile;
    # None: the built-in robot on qnav's own frames)
    robot: Any = None
    flip_wheel: str = ""  # "left" / "right": that motor mounted the other way round (bring-up checks)
    drive_faults: tuple[tuple[float, str, str], ...] = ()  # (sim s, "error:0x800" | "silent", "left" | "right")

    @classmethod
    def from_profile(cls, profile: PlantProfile, **kw: Any) -> SimConfig:
        """A config with a named profile's wheel and sensor error (sim_bridge.profiles)."""
        return cls(ranges=RangeParams(noise_std_mm=profile.range_noise_mm, dropout=profile.range_dropout),
                   encoder_slip_std=profile.slip_std, encoder_scale=profile.encoder_scale, **kw)


@dataclass
class RunStats:
    ticks: int = 0
    missed_ticks: int = 0
    stale_commands: int = 0  # lockstep: MotorCommands for a tick that is not the current one (and was not answered)
    repeated_answers: int = 0  # lockstep: a second answer to the tick just answered (the controller saw a resent SimTick)
    bad_frames: int = 0
    frames_sent: int = 0
    frames_received: int = 0
    wall_s: float = 0.0
    start_wait_s: float = 0.0  # lockstep: wall time until the controller's first answer
    sim_s: float = 0.0
    # paced (and lockstep with a max speed): wall seconds the schedule was let slip because the
    # loop fell more than a control period behind it (a stalled process), instead of catching up
    slipped_s: float = 0.0

    @property
    def ticks_per_s(self) -> float:
        """Control ticks per wall second once the controller is up."""
        busy = self.wall_s - self.start_wait_s
        return self.ticks / busy if busy > 0 else float("inf")


class Plant:
    """World + sensors + motor driver, speaking qnav CAN frames."""

    def __init__(self, occ: np.ndarray, config: SimConfig | None = None,
                 start: Pose | None = None) -> None:
        config = config if config is not None else SimConfig()
        self.config = config
        robot = config.robot
        self.profile = robot if robot is not None else DEFAULT_ROBOT  # the one robot every part below plays
        sensors = self.profile.sensors
        if sensors.backend == "qnav" and len(sensors.angles_deg) != robot_spec.SENSOR_COUNT:
            raise ValueError(f"{len(sensors.angles_deg)} range sensors: qnav's RangeSectors frames carry "
                             f"{robot_spec.SENSOR_COUNT}; another count needs the dronecan sensor backend")
        self.world = World(occ, config.cell_size_m, start, config.body, self.profile.geometry)
        # one seeded stream per noise source, so changing one model leaves the others alone
        seeds = random.Random(config.seed)
        self.ranges = RangeSensors(self.world, config.ranges, random.Random(seeds.getrandbits(64)), sensors)
        self.encoders = WheelEncoders(self.world, random.Random(seeds.getrandbits(64)),
                                      config.encoder_slip_std, config.encoder_scale)
        self.odrive: Any = None  # sim_bridge.odrive_axes.ODrivePair when the robot's drive is two ODrives
        self.dronecan: Any = None  # sim_bridge.dronecan_boards.DroneCanBoards: DroneCAN ESCs and/or rangefinders
        # the robot's tick ends with a SimTickAck unless its drive is qnav's (MotorCommand carries the counter)
        self.answer_is_ack = robot is not None and robot.drive.backend != "qnav"
        if robot is not None and "dronecan" in (robot.drive.backend, robot.sensors.backend):
            try:
                from sim_bridge.dronecan_boards import DroneCanBoards
            except ImportError:
                raise ValueError("the sim's DroneCAN boards need the dronecan library: "
                                 "pip install 'qnav[dronecan]'") from None
            on_drive = robot.drive.backend == "dronecan"
            self.motors = MotorDriver(replace(config.motors, watchdog_ms=1 << 30) if on_drive else config.motors)
            self.dronecan = DroneCanBoards(robot, self.motors, drive=on_drive,
                                           sensors=robot.sensors.backend == "dronecan", flip=config.flip_wheel)
            self.dronecan.faults = [(round(t * 1e6), what, side) for t, what, side in config.drive_faults]
        if robot is not None and robot.drive.backend == "odrive":
            from sim_bridge.odrive_axes import ODrivePair
            # the axes' own watchdog stops the wheels; the wheel model's is out of the way
            self.motors = MotorDriver(replace(config.motors, watchdog_ms=1 << 30))
            self.odrive = ODrivePair(robot, self.motors, config.flip_wheel)
            self.odrive.faults = [(round(t * 1e6), what, side) for t, what, side in config.drive_faults]
        elif self.dronecan is None:
            self.motors = MotorDriver(config.motors)
        self.battery = Battery()
        self.tick = 0
        self.time_us = 0
        self.stats = RunStats()
        self.trajectory: list[tuple] = []
        self._answered_tick: int | None = None  # counter of the last tick the controller answered (lockstep)
        self._last_cmd = (0, 0)
        self.obstacles: Any = None  # a sim_bridge.obstacles.ObstacleLayer: its movers move once per period
        self._interrupt_pending = False  # a SIGINT waiting for a safe point (interrupt)
        if self.odrive is not None:
            self.odrive.step(0, self.encoders.wheel_turns())
        self.record()

    # --- frames out ----------------------------------------------------------
    def tick_frames(self) -> list[can.Message]:
        """All frames of the current control tick, sampled now; SimTick last."""
        t_s = self.time_us / 1e6
        left, right = self.encoders.counts()
        readings = self.ranges.read()
        dc = self.dronecan
        # one new sample per tick: counter = tick
        frames = cp.range_frames(readings, self.tick) if dc is None or not dc.sensors else []
        if self.odrive is None and (dc is None or not dc.drive):
            frames.append(cp.encoder_counts(left, right, self.tick))
        frames.append(cp.encode("Bumper", bumper_signals(self.world, self.tick)))
        if self.odrive is not None:
            frames += self.odrive.drain()  # heartbeats and encoder estimates due since the last tick
        elif dc is None or not dc.drive:
            frames.append(cp.encode("MotorStatus", self.motors.status(self.tick)))
        if dc is not None:
            frames += dc.tick_frames(readings)  # ESC Status, range Measurements, NodeStatus
        if self.tick % BATTERY_EVERY_TICKS == 0:  # the power board reports at 2 Hz
            frames.append(cp.encode("BatteryStatus", self.battery.status(self.tick // BATTERY_EVERY_TICKS)))
        frames.append(cp.sim_tick(self.tick, self.time_us))
        for f in frames:
            f.timestamp = t_s
        return frames

    # --- frames in -----------------------------------------------------------
    def handle(self, msg: can.Message, lockstep: bool = True) -> bool:
        """Apply a received frame at the current sim time.

        Returns True when `msg` is the controller's answer to the current tick
        (a MotorCommand carrying its counter; in paced mode any MotorCommand).
        """
        if self.odrive is not None and self.odrive.owns(msg):
            self.odrive.handle(msg, self.time_us)
            return False
        if self.dronecan is not None and self.dronecan.owns(msg):
            self.dronecan.handle(msg, self.time_us)
            return False
        try:
            name, sig = cp.decode(msg)
        except cp.ProtocolError:
            self.stats.bad_frames += 1
            if msg.arbitration_id == cp.MOTOR_COMMAND_ID:
                self.motors.bad_command()
            return False
        if name == "MotorCommand":
            if not self._answers_tick(sig["Cmd_Counter"], lockstep):
                return False
            left, right = sig["Cmd_LeftSpeed"], sig["Cmd_RightSpeed"]
            if self.config.flip_wheel:  # a motor mounted the other way round turns its wheel backwards
                left, right = (-left, right) if self.config.flip_wheel == "left" else (left, -right)
            self.motors.command(left, right, sig["Cmd_Counter"], self.time_us)
            self._last_cmd = (sig["Cmd_LeftSpeed"], sig["Cmd_RightSpeed"])
            return True
        if name == "SimTickAck" and self.answer_is_ack:  # the answer when the drive's frames carry no counter
            if not self._answers_tick(sig["Ack_Counter"], lockstep):
                return False
            self._last_cmd = (round(self.motors.target[0]), round(self.motors.target[1]))
            return True
        if name == "EStop":
            self.motors.estop(bool(sig["EStop_Engage"]))
        return False

    def _answers_tick(self, counter: int, lockstep: bool) -> bool:
        """Whether a frame carrying `counter` answers the current tick (always, when paced); a lockstep
        answer is remembered. The sim resends a SimTick the controller is slow to answer, and the
        controller answers each copy: the second answer to a tick already answered is a repeat, not a
        stale command."""
        if not lockstep:
            return True
        if counter != self.tick % cp.TICK_MODULUS:
            if counter == self._answered_tick:
                self.stats.repeated_answers += 1
            else:
                self.stats.stale_commands += 1
            return False
        self._answered_tick = counter
        return True

    # --- physics ---------------------------------------------------------------
    def step_period(self) -> None:
        """Advance one control period in fixed physics steps, then record the pose."""
        dt_us = robot_spec.PHYSICS_DT_US
        dt_s = dt_us / 1e6
        world, motors, encoders = self.world, self.motors, self.encoders
        self._physics(dt_us, dt_s, world, motors, encoders)
        self.check_interrupt()

    def interrupt(self) -> None:
        """SIGINT handler body: KeyboardInterrupt at the next `check_interrupt` (the end of a
        physics step, or between two of the run loop's bus reads), never where the signal lands:
        raised inside a pymunk contact callback cffi would print and swallow it (the sim ran on);
        raised inside a bus call, between a python-can-remote frame's header and its body, the
        stream to the hub is out of step and the bus's shutdown fails."""
        self._interrupt_pending = True

    def check_interrupt(self) -> None:
        """Raise the KeyboardInterrupt a SIGINT asked for (`interrupt`), if any."""
        if self._interrupt_pending:
            self._interrupt_pending = False
            raise KeyboardInterrupt

    def _physics(self, dt_us: int, dt_s: float, world: Any, motors: Any, encoders: Any) -> None:
        for _ in range(STEPS_PER_TICK):
            self.time_us += dt_us
            left, right = motors.step(dt_us, self.time_us)
            self.battery.step(dt_s, left, right)
            world.drive(left / 1000, right / 1000)
            encoders.integrate(dt_s)  # pymunk moves the body by its pre-step velocity
            world.step(dt_s)
            gl, gr = world.wheel_ground_speeds()
            motors.observe_ground((gl * 1000, gr * 1000), dt_us)
            if self.odrive is not None:
                self.odrive.step(self.time_us, encoders.wheel_turns())
            elif self.dronecan is not None:
                self.dronecan.step(self.time_us)
        if self.obstacles is not None:
            self.obstacles.step()
        self.tick += 1
        self.stats.ticks += 1
        self.stats.sim_s = self.time_us / 1e6
        self.record()

    def record(self) -> None:
        pose = self.world.pose
        self.trajectory.append((
            self.time_us / 1e6, self.tick, pose.x, pose.y, pose.heading,
            self.motors.speed[0], self.motors.speed[1], self._last_cmd[0], self._last_cmd[1],
            int(bool(self.world.contacts))))


# --- shells: move frames over a bus ------------------------------------------------

class _Io:
    def __init__(self, plant: Plant, bus: can.BusABC, logger: can.Listener | None) -> None:
        self.plant, self.bus, self.logger = plant, bus, logger

    def send(self, frames: list[can.Message]) -> None:
        for f in frames:
            self.bus.send(f)
            if self.logger is not None:
                self.logger.on_message_received(f)
        self.plant.stats.frames_sent += len(frames)

    def recv(self, timeout: float) -> can.Message | None:
        msg = self.bus.recv(timeout=max(0.0, timeout))
        if msg is not None:
            self.plant.stats.frames_received += 1
            msg.timestamp = self.plant.time_us / 1e6  # logs are in sim time
            msg.is_rx = True
            if self.logger is not None:
                self.logger.on_message_received(msg)
        return msg


def run_lockstep(plant: Plant, bus: can.BusABC, duration_s: float, *,
                 logger: can.Listener | None = None, tick_timeout_s: float = 1.0,
                 start_timeout_s: float = 30.0, resend_s: float = 0.2,
                 progress=None, on_wait: Callable[[str], None] | None = None,
                 wait_notice_s: float = 1.0, max_speed: float | None = None) -> RunStats:
    """Lockstep until `duration_s` of sim time: each tick waits for its MotorCommand.
    `on_wait(line)` is told once what the sim waits for when the controller's
    first answer has not come within `wait_notice_s`. `max_speed`: never run faster
    than that many times real time (for links that are real-time, such as a radio,
    while a loaded machine only slows the run: no tick is ever stepped unanswered)."""
    if max_speed is not None and not max_speed > 0:
        raise ValueError(f"max_speed must be positive, got {max_speed}")
    io = _Io(plant, bus, logger)
    stats = plant.stats
    end_us = round(duration_s * 1e6)
    started = False
    t0 = time.perf_counter()
    pace = None
    while plant.time_us < end_us:
        frames = plant.tick_frames()
        io.send(frames)
        now = time.perf_counter()
        deadline = now + (tick_timeout_s if started else start_timeout_s)
        next_resend = now + resend_s
        answered = False
        while not answered:
            msg = io.recv(min(deadline, next_resend) - now)
            plant.check_interrupt()  # within resend_s of a Ctrl-C, however long the controller takes
            if msg is not None:
                answered = plant.handle(msg, lockstep=True)
            now = time.perf_counter()
            if answered or now >= deadline:
                break
            if on_wait is not None and not started and now - t0 >= wait_notice_s:
                on_wait(f"waiting for a controller to answer SimTick 0 with a MotorCommand "
                        f"(e.g. qnav-robot --lockstep on the same --can bus), up to {start_timeout_s:g} s ...")
                on_wait = None
            if now >= next_resend:
                io.send(frames[-1:])  # the SimTick again (lost frame, late controller)
                next_resend = now + resend_s
        if not answered:
            if not started:
                raise LockstepError(f"no controller answered SimTick 0 within {start_timeout_s:g} s")
            stats.missed_ticks += 1
        if not started:
            stats.start_wait_s = time.perf_counter() - t0
            if max_speed is not None:
                pace = _Pace(plant, max_speed)
        started = True
        _end_period(plant, t0, progress)
        if pace is not None:
            time.sleep(pace.wait_s())
    stats.wall_s = time.perf_counter() - t0
    return stats


class _Pace:
    """The wall-clock schedule of a paced loop: sim time t is due at base + t / speed.

    A loop more than one control period behind (its process stalled) lets the
    schedule slip instead of catching up: a burst of unanswered ticks would trip the
    motor driver's watchdog (sim time) on a robot that did nothing wrong."""

    def __init__(self, plant: Plant, speed: float, clock: Callable[[], float] = time.perf_counter) -> None:
        self.plant = plant
        self.speed = speed
        self.clock = clock
        self.base = clock() - plant.time_us / 1e6 / speed

    def due(self) -> float:
        """Wall time at which the next period may start."""
        return self.base + self.plant.time_us / 1e6 / self.speed

    def wait_s(self) -> float:
        """Seconds to wait now; slips the schedule when it is behind by more than a period."""
        late = self.clock() - self.due()
        period_s = robot_spec.CONTROL_PERIOD_US / 1e6 / self.speed
        if late > period_s:
            self.base += late
            self.plant.stats.slipped_s += late
            return 0.0
        return max(0.0, -late)


def _end_period(plant: Plant, t0: float, progress: Any) -> None:
    """Step the physics over one control period and account for it."""
    plant.step_period()
    plant.stats.wall_s = time.perf_counter() - t0  # kept current: a Ctrl-C ends the loop anywhere
    if progress is not None:
        progress.update(1)


def run_paced(plant: Plant, bus: can.BusABC, duration_s: float, speed: float = 1.0, *,
              logger: can.Listener | None = None, progress=None) -> RunStats:
    """Send each tick at wall time t_k / speed, never wait for the controller; a loop
    that fell more than a period behind (a stall) slips its schedule (RunStats.slipped_s)."""
    if not speed > 0:
        raise ValueError(f"speed must be positive, got {speed}")
    io = _Io(plant, bus, logger)
    stats = plant.stats
    end_us = round(duration_s * 1e6)
    t0 = time.perf_counter()
    pace = _Pace(plant, speed)
    while plant.time_us < end_us:
        io.send(plant.tick_frames())
        pace.wait_s()  # slips the schedule if this loop fell behind (a stall), no burst
        wake = pace.due() + robot_spec.CONTROL_PERIOD_US / 1e6 / speed
        while True:
            remaining = wake - time.perf_counter()
            if remaining <= 0:
                break
            msg = io.recv(remaining)
            plant.check_interrupt()
            if msg is not None:
                plant.handle(msg, lockstep=False)
        while (msg := io.recv(0.0)) is not None:  # frames that arrived meanwhile
            plant.handle(msg, lockstep=False)
        _end_period(plant, t0, progress)
    stats.wall_s = time.perf_counter() - t0
    return stats
