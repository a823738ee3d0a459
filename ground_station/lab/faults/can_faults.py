"""CAN fault scenarios against the controller on a real bus with the pymunk plant.

Each trial drives the shipped paper10 cell policy from a seeded random start
towards a target several cells away (lockstep, `rigs.lockstep.LockstepRig`), then
injects one fault at a seeded random moment while it is DRIVING:

- `can_sensor_stop`: a random non-empty set of the input frames (range
  boards, encoders, bumper, motor status) stops, with a random staleness
  timeout (100/250/500 ms): the commands are zero, and stay zero, no later
  than the last fresh sample + timeout + one control period; FAULT.
- `can_driver_fault`: the motor driver reports error bits (stall, bad
  command) from one tick on: FAULT and zero command at that very tick.
- `can_driver_watchdog`: the controller's commands stop reaching the driver
  (cut wire); the driver's watchdog trips and says so: FAULT and zero
  commands within the driver watchdog + two periods of the last command.
- `can_estop`: an EStop frame from another node: FAULT and zero command at
  that tick; the latch survives the e-stop's release (arm refused) until a
  disarm; then arming works again.
- `can_counters`: every tick, seeded duplicates of sensor frames and of the
  SimTick, replays of older SimTicks (out-of-order counters) and stale
  motor commands offered to the driver: the episode still reaches its goal,
  every real tick is stepped exactly once, no replayed tick is stepped or
  counted as an overrun.
- `can_garbage`: paced HIL in real time (sim clock, as across processes)
  with random garbage frames at 5 kHz on the same bus: unknown ids (11 and
  29 bit), the controller's input ids with wrong lengths, remote and error
  frames. Every control tick still runs (no overrun, ticks == sim ticks),
  every garbage frame is counted as a CAN error, the robot keeps driving.
"""

from __future__ import annotations

import random
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import can

from firmware_py import can_protocol as cp
from firmware_py.vehicle import CtrlState, VehicleConfig
from ground_station.lab.faults.common import ScenarioResult, register, trials
from ground_station.lab.rigs.lockstep import PERIOD_US, LockstepRig, cell_policy, far_trip, paper10

INPUT_FRAMES = ("RangeSectors0", "RangeSectors1", "EncoderCounts", "Bumper", "MotorStatus")


def _zero(cmd: tuple[int, ...]) -> bool:
    return cmd[1] == 0 and cmd[2] == 0


def _fault_time(rng: random.Random) -> int:
    """A tick time 1.0 .. 3.0 s into the episode (the robot is driving by then)."""
    return rng.randrange(20, 61) * PERIOD_US


def _setup(seed: int, vehicle: VehicleConfig | None = None):
    rng = random.Random(seed)
    gm, pol = paper10(), cell_policy()
    start, goal = far_trip(gm, pol, rng)
    return rng, LockstepRig(gm.occ, pol, start, [goal], seed=seed, vehicle=vehicle)


def _episodes(count: int, first_seed: int, progress: Any = None) -> Iterator[tuple[int, random.Random, Any, int]]:
    """(i, rng, rig, t_fault) of `count` seeded episodes (seeds first_seed + i), `progress` ticked
    after each; t_fault, the episode's first draw, is when its fault comes (`_fault_time`)."""
    for i in trials(count, progress):
        rng, rig = _setup(first_seed + i)
        yield i, rng, rig, _fault_time(rng)


def _stale_episodes(count: int, first_seed: int,
                    progress: Any = None) -> Iterator[tuple[int, random.Random, Any, int, int]]:
    """As `_episodes`, for faults judged by the staleness timeout: (i, pick, rig, t_fault, timeout_ms),
    the controller's timeout (100/250/500 ms) the first draw of `pick`, the seeded source the
    scenario then draws the rest of its fault from."""
    for i in trials(count, progress):
        pick = random.Random(first_seed + i)
        timeout_ms = pick.choice((100, 250, 500))
        rng, rig = _setup(first_seed + i, VehicleConfig(sensor_timeout_ms=timeout_ms))
        yield i, pick, rig, _fault_time(rng), timeout_ms


def _zero_from(rig: LockstepRig, t_us: int) -> list[str]:
    late = [c for c in rig.commands if c[0] >= t_us and not _zero(c)]
    return [f"non-zero command {late[0][1:3]} at t={late[0][0]} us after the stop"] if late else []


def _stopped_by(rig: LockstepRig, t_us: int, deadline_us: int) -> list[str]:
    """Problems unless the first zero command from `t_us` on came by
    `deadline_us` and every command after it is zero."""
    zeros = [c[0] for c in rig.commands if c[0] >= t_us and _zero(c)]
    if not zeros or zeros[0] > deadline_us:
        return [f"first zero command at {zeros[0] if zeros else None} us > deadline {deadline_us}"]
    return _zero_from(rig, zeros[0])


def _first_fault(rig: LockstepRig, after_us: int):
    return rig.first_transition_to(CtrlState.FAULT, after_us)


def _fault_at(rig: LockstepRig, t_us: int, cause: str = "") -> list[str]:
    """Problems unless the controller went to FAULT at tick `t_us` itself (its cause containing
    `cause`) and every command from that tick on is zero: the stop at the very tick the fault shows."""
    fault = _first_fault(rig, t_us)
    problems = _zero_from(rig, t_us)
    if fault is None or fault.t_us != t_us or cause not in fault.cause:
        problems.insert(0, f"FAULT transition {fault}, expected {cause or 'one'} at {t_us} us")
    return problems


def _fault_by(rig: LockstepRig, t_us: int, deadline_us: int) -> list[str]:
    """Problems unless the controller went to FAULT between `t_us` and `deadline_us`."""
    fault = _first_fault(rig, t_us)
    return [f"no FAULT by {deadline_us} us ({fault})"] if fault is None or fault.t_us > deadline_us else []


def _drive_to(rig: LockstepRig, t_us: int, when: str, problems: list[str], **kw: Any) -> None:
    """Run `rig` to `t_us` (`kw` as for `LockstepRig.tick`), where a scenario injects its fault;
    a setup problem, said `when`, unless the robot is DRIVING then: a fault injected into a
    robot that stands still proves nothing about stopping it."""
    rig.run_until(t_us, **kw)
    if rig.ctrl.state != CtrlState.DRIVING:
        problems.append(f"setup: {rig.ctrl.state.name} {when}, not DRIVING")


def _stale_deadline(t_us: int, timeout_us: int) -> int:
    """When the controller must have stopped for inputs that stop being new at tick `t_us`: the
    last new sample came one period before, goes stale `timeout_us` later, and the next control
    tick sees it within one more period."""
    return t_us - PERIOD_US + timeout_us + PERIOD_US


def _drive_stale(rig: LockstepRig, t_us: int, timeout_ms: int, when: str, hook: Callable) -> tuple[list[str], int]:
    """Run `rig` with `hook` on its frames to `t_us`, where inputs stop being new (`_drive_to`, said
    `when`), and on past the staleness deadline: (problems unless the commands stopped by the
    deadline and stayed zero, the deadline)."""
    problems: list[str] = []
    with rig:
        _drive_to(rig, t_us, when, problems, frames_hook=hook)
        deadline = _stale_deadline(t_us, timeout_ms * 1000)
        rig.run_until(deadline + 4 * PERIOD_US, frames_hook=hook)
    return problems + _stopped_by(rig, t_us, deadline), deadline


def _edit_after(t_from_us: int, message: str, edit: Callable[[dict], None]):
    """A frames hook that decodes every `message` frame from `t_from_us` on,
    lets `edit` change its signals in place and re-encodes it (a board that
    starts lying at a given tick)."""
    fid = cp.FRAME_IDS[message]

    def hook(_tick, t_us, frames):
        if t_us < t_from_us:
            return frames
        out = []
        for f in frames:
            if f.arbitration_id == fid:
                _, sig = cp.decode(f)
                edit(sig)
                f = cp.encode(message, sig)
            out.append(f)
        return out
    return hook


@register("can_sensor_stop", small=4, large=100, unit="episodes",
          what="input frames stop -> zero command within staleness timeout + 1 period, FAULT")
def sensor_stop(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    for i, pick, rig, t_cut, timeout_ms in _stale_episodes(count, seed * 7919, progress):
        cut = set(pick.sample(INPUT_FRAMES, pick.randint(1, len(INPUT_FRAMES))))
        ids = {cp.FRAME_IDS[n] for n in cut}

        def hook(_tick, t_us, frames, ids=ids, t_cut=t_cut):
            return frames if t_us < t_cut else [f for f in frames if f.arbitration_id not in ids]

        problems, deadline = _drive_stale(rig, t_cut, timeout_ms, "at the cut", hook)
        problems += _fault_by(rig, t_cut, deadline)
        res.check(problems, f"seed {seed}/{i} cut {sorted(cut)} at {t_cut} us, timeout {timeout_ms} ms")


@register("can_driver_fault", small=3, large=60, unit="episodes",
          what="motor driver error bits -> FAULT and zero command at that tick")
def driver_fault(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    for i, rng, rig, t_fault in _episodes(count, seed * 7919 + 1000, progress):
        bits = rng.randint(1, 7)

        def set_errors(sig: dict, bits: int = bits) -> None:
            sig["Mot_Errors"] = bits

        hook = _edit_after(t_fault, "MotorStatus", set_errors)

        problems: list[str] = []
        with rig:
            _drive_to(rig, t_fault, "at the fault", problems, frames_hook=hook)
            rig.run_until(t_fault + 6 * PERIOD_US, frames_hook=hook)
        problems += _fault_at(rig, t_fault)
        res.check(problems, f"seed {seed}/{i} errors 0x{bits:02x} at {t_fault} us")


@register("can_driver_watchdog", small=3, large=60, unit="episodes",
          what="commands stop reaching the driver -> its watchdog trips -> controller FAULT")
def driver_watchdog(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    for i, _, rig, t_cut in _episodes(count, seed * 7919 + 2000, progress):
        wd_us = rig.plant.motors.p.watchdog_ms * 1000
        problems: list[str] = []
        with rig:
            _drive_to(rig, t_cut, "at the cut", problems)
            last_cmd = t_cut - PERIOD_US  # the last answer the driver received
            deadline = last_cmd + wd_us + 2 * PERIOD_US
            rig.run_until(deadline + 4 * PERIOD_US, deliver=False)
        tripped = rig.plant.motors.watchdog_tripped
        fault = _first_fault(rig, t_cut)
        if not tripped:
            problems.append("setup: the driver watchdog did not trip")
        if fault is None or fault.t_us > deadline:
            problems.append(f"no FAULT by {deadline} us ({fault})")
        else:
            problems += _zero_from(rig, fault.t_us)
        res.check(problems, f"seed {seed}/{i} commands cut at {t_cut} us")


@register("can_estop", small=3, large=60, unit="episodes",
          what="EStop from another node -> FAULT + zero at that tick; latched until disarm")
def estop(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    senders = [n for n in (cp.NODE_BROADCAST, cp.NODE_MOTOR_DRIVER, cp.NODE_RANGE_BOARD,
                           cp.NODE_BUMPER_BOARD, cp.NODE_SIM) if n != cp.NODE_CONTROLLER]
    for i, rng, rig, t_stop in _episodes(count, seed * 7919 + 3000, progress):
        source = rng.choice(senders)
        hold_ticks = rng.randint(1, 10)
        problems: list[str] = []

        def frame(engage: int, source=source, rng=rng):
            return cp.encode("EStop", {"EStop_Engage": engage, "EStop_Source": source,
                                       "EStop_Reason": rng.randrange(256)})

        with rig:
            _drive_to(rig, t_stop, "before the e-stop", problems)
            rig.send(frame(1))
            for _ in range(hold_ticks):
                rig.tick()
            rig.send(frame(0))
            rig.tick()
            rig.tick()
            ok, why = rig.ctrl.arm()  # already armed (FAULT keeps armed) -> must not clear
            ok_goal, _ = rig.ctrl.go_to(*rig.runner.goals[0])
            if ok_goal:
                problems.append("a goal was accepted while the e-stop was latched")
            rig.tick()
            rig.ctrl.disarm()
            rig.tick()
            ok, why = rig.ctrl.arm()
            if not ok:
                problems.append(f"arm after release + disarm refused: {why}")
            rig.tick()
        problems += _fault_at(rig, t_stop, "e-stop")
        res.check(problems, f"seed {seed}/{i} e-stop from node {source} at {t_stop} us")


@register("can_counters", small=2, large=30, unit="episodes",
          what="duplicated/out-of-order frames and counters: goal reached, each tick stepped once")
def counters(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    injected = {"dup_sensor": 0, "dup_tick": 0, "old_tick": 0, "stale_cmd": 0}
    for i in trials(count, progress):
        rng, rig = _setup(seed * 7919 + 4000 + i)
        history: list[can.Message] = []  # earlier SimTicks, for replays
        late = [0]  # replays older than the last tick: the robot must count each in late_ticks

        def hook(tick, _t, frames, rng=rng, history=history, late=late):
            sim_tick = frames[-1]
            out = []
            if history and rng.random() < 0.2:  # an older tick arrives late, before this one
                old = rng.choice(history[-4:])
                out.append(old)
                injected["old_tick"] += 1
                late[0] += old is not history[-1]  # the last tick again is a resend, not a late tick
            for f in frames[:-1]:
                out.append(f)
                if rng.random() < 0.3:
                    out.append(f)
                    injected["dup_sensor"] += 1
            out.append(sim_tick)
            if rng.random() < 0.2:
                out.append(sim_tick)
                injected["dup_tick"] += 1
            history.append(sim_tick)
            return out

        problems: list[str] = []

        def stale_command(rig=rig, rng=rng, problems=problems):
            if rig.plant.tick > 4 and rng.random() < 0.2:  # an old command reaches the driver late
                old = rig.plant.tick - rng.randint(1, 4)
                st = rig.plant.stats
                before = (st.stale_commands + st.repeated_answers, rig.plant.motors.commands)
                # refused and counted: stale, or a repeat when it carries the tick just answered
                took = rig.plant.handle(cp.motor_command(600, -600, old), lockstep=True)
                injected["stale_cmd"] += 1
                if took or (st.stale_commands + st.repeated_answers, rig.plant.motors.commands) != (before[0] + 1,
                                                                                                  before[1]):
                    problems.append(f"driver applied a stale command for tick {old}")

        with rig:
            while rig.plant.time_us < 90_000_000 and not rig.runner.done.is_set():
                rig.tick(frames_hook=hook, before_answer=stale_command)
            st = rig.ctrl.status()
            overruns = rig.node.overruns
            late_counted = rig.node.late_ticks
        if late_counted != late[0]:
            problems.append(f"{late[0]} late (older) ticks replayed, {late_counted} counted in late_ticks")
        if rig.runner.result != "reached":
            problems.append(f"episode ended {rig.runner.result or 'in timeout'}")
        if st.ticks != rig.plant.tick:
            problems.append(f"controller stepped {st.ticks} times for {rig.plant.tick} ticks")
        if rig.stale_answers:
            problems.append(f"{rig.stale_answers} replayed ticks were stepped and answered")
        if overruns:
            problems.append(f"{overruns} overruns counted (no tick was lost)")
        res.check(problems, f"seed {seed}/{i}")
    res.figures.update(injected)


# --- garbage at 5 kHz, paced in real time --------------------------------------------------

_OWN_IDS = {cp.MOTOR_COMMAND_ID, cp.CONTROLLER_HEARTBEAT_ID}  # only the controller sends these
_INPUT_IDS = sorted(cp.FRAME_IDS[n] for n in (*INPUT_FRAMES, "EStop", "SimTick"))
_KNOWN_IDS = set(cp.FRAME_IDS.values())


def garbage_frame(rng: random.Random) -> can.Message:
    """One frame no node of ours sends: see the module docstring."""
    r = rng.random()
    if r < 0.6:  # an 11-bit id of no node, any length
        fid = rng.randrange(0x800)
        while fid in _KNOWN_IDS:
            fid = rng.randrange(0x800)
        return can.Message(arbitration_id=fid, is_extended_id=False, data=rng.randbytes(rng.randint(0, 8)))
    if r < 0.8:  # an input id of ours with a wrong length
        fid = rng.choice(_INPUT_IDS)
        want = cp.DB.get_message_by_frame_id(fid).length
        n = rng.choice([k for k in range(9) if k != want])
        return can.Message(arbitration_id=fid, is_extended_id=False, data=rng.randbytes(n))
    if r < 0.9:  # 29-bit id whose low bits alias one of ours
        fid = (rng.randrange(1, 1 << 18) << 11) | rng.choice(_INPUT_IDS)
        return can.Message(arbitration_id=fid, is_extended_id=True, data=rng.randbytes(8))
    if r < 0.95:
        return can.Message(arbitration_id=rng.choice(_INPUT_IDS), is_extended_id=False,
                           is_remote_frame=True, dlc=8)
    return can.Message(arbitration_id=0, is_error_frame=True, data=rng.randbytes(rng.randint(0, 8)))


class GarbageSender:
    """A thread putting `rate_hz` garbage frames per wall second on `bus`."""

    def __init__(self, bus: can.BusABC, rate_hz: float, seed: int) -> None:
        self.bus, self.rate_hz = bus, rate_hz
        self.rng = random.Random(seed)
        self.sent = 0
        self.seconds = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="can-garbage", daemon=True)

    def _run(self) -> None:
        t0 = time.perf_counter()
        while not self._stop.is_set():
            due = int((time.perf_counter() - t0) * self.rate_hz)
            while self.sent < due:
                self.bus.send(garbage_frame(self.rng))
                self.sent += 1
            time.sleep(0.001)
        self.seconds = time.perf_counter() - t0

    def __enter__(self) -> GarbageSender:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


def garbage_run(duration_s: float, seed: int, rate_hz: float = 5000.0) -> dict:
    """One paced real-time HIL run with garbage; returns the measured figures."""
    from firmware_py.clock import SimClock
    from firmware_py.control.controller import Controller
    from firmware_py.control.goals import GoalRunner
    from firmware_py.control.node import RobotNode
    from sim_bridge.plant import Plant, SimConfig, run_paced
    from sim_bridge.world import Pose

    rng = random.Random(seed)
    gm, pol = paper10(), cell_policy()
    start, goal = far_trip(gm, pol, rng, min_cells=8)
    channel = f"garbage-{uuid.uuid4().hex}"
    buses = [can.Bus(interface="virtual", channel=channel) for _ in range(3)]
    sim_bus, node_bus, junk_bus = buses
    plant = Plant(gm.occ, SimConfig(seed=seed), Pose(*start))
    ctrl = Controller(VehicleConfig(), pol, start_pose_mm=(round(start[0] * 1000), round(start[1] * 1000),
                                                          round(start[2] * 1000)))
    node = RobotNode(node_bus, ctrl, SimClock())
    runner = GoalRunner(ctrl, [goal])
    node.after_tick.append(runner)
    try:
        node.start()
        with GarbageSender(junk_bus, rate_hz, seed) as junk:
            run_paced(plant, sim_bus, duration_s, speed=1.0)
        # let the receive thread work off its queue before reading the counters
        settle = time.monotonic() + 5.0
        while node.can_errors < junk.sent and time.monotonic() < settle:
            time.sleep(0.02)
        time.sleep(0.1)
    finally:
        node.stop()
        for b in buses:
            b.shutdown()
    st = ctrl.status()
    return {"duration_s": duration_s, "garbage_sent": junk.sent,
            "garbage_rate_hz": junk.sent / junk.seconds if junk.seconds else 0.0,
            "can_errors": node.can_errors, "sim_ticks": node.sim_ticks, "ticks": node.ticks,
            "overruns": node.overruns, "plant_bad_frames": plant.stats.bad_frames,
            "state": st.state.name, "fault": st.fault, "result": runner.result,
            "transitions": [(t.t_us, t.src.name, t.dst.name, t.cause) for t in ctrl.transitions]}


@register("can_garbage", small=1, large=5, unit="runs of 4 s (test) / 20 s (bench) at 5 kHz",
          what="garbage frames at 5 kHz: every tick runs, every garbage frame counted, no fault")
def garbage(res: ScenarioResult, count: int, seed: int, progress: Any, duration_s: float | None = None) -> None:
    if duration_s is None:
        duration_s = 4.0 if count <= 1 else 20.0
    runs = []
    for i in trials(count, progress):
        fig = garbage_run(duration_s, seed * 7919 + 5000 + i)
        runs.append({k: v for k, v in fig.items() if k != "transitions"})
        problems: list[str] = []
        if fig["overruns"]:
            problems.append(f"{fig['overruns']} control ticks missed")
        if fig["ticks"] != fig["sim_ticks"]:
            problems.append(f"{fig['ticks']} control ticks for {fig['sim_ticks']} sim ticks")
        if fig["can_errors"] != fig["garbage_sent"]:
            problems.append(f"{fig['can_errors']} CAN errors counted for {fig['garbage_sent']} garbage frames")
        if fig["state"] == "FAULT" or not any(t[2] == "DRIVING" for t in fig["transitions"]):
            problems.append(f"state {fig['state']} {fig['fault']}")
        res.check(problems, f"seed {seed}/{i}")
    res.figures["runs"] = runs
    res.figures["garbage_frames"] = sum(r["garbage_sent"] for r in runs)
    res.figures["min_rate_hz"] = min((r["garbage_rate_hz"] for r in runs), default=0.0)
