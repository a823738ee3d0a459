"""The DroneCAN backend fed until it stalls (issue 43, finding 4), one scenario each.

The real robot on the in-process lockstep rig (`rigs.lockstep.LockstepRig`: the pymunk plant with
its DroneCAN ESC and rangefinder nodes of the `dronecan` library, the real RobotNode + Controller
with the `dronecan` drive and sensor backends, firmware_py/profiles/dronecan.toml, node id 100, on
a python-can virtual bus); the hostile frames are built with the `dronecan` library and put on
the bus by another node:

- `dronecan_reassembly_flood`: one multi-frame transfer is started and fed 100,000 continuation
  frames (the right toggle bits, 1,000 a tick), then its end frame. A transfer of a known type
  (debug.LogMessage, at most 123 bytes) or of a type id nobody knows. Held: the memory allocated
  over the flood (tracemalloc, the whole process: the rig's own per-tick records included) < 1 MB,
  the tick that carries the end frame and that frame's handling (the backend's `take`) under the
  control period (50 ms), every tick answered, no FAULT. Reported, not held: the longest single
  frame's handling and tick during the flood (the receive thread takes 1,000 frames a tick under
  tracemalloc: GIL hand-offs and garbage collection, tens of ms on a loaded 2-core machine).
- `dronecan_service_flood`: 50 GetNodeInfo requests (from 50 node ids) arrive in one tick while
  driving. Held: no service-answer frame goes out ahead of that tick's wheel command
  (esc.RPMCommand), at most one answer's frames follow it in a tick, and the requesters are still
  answered over the next ticks (at the backend's rate: one a tick, 10 a second, 16 requesters
  pending at most; the rest are dropped and ask again, as a node monitor does).
- `dronecan_node_id_collision`: another node broadcasts NodeStatus with the robot's own node id
  (100) at 1 Hz. Held: the robot refuses to arm with a text naming the id (a STATUSTEXT), the
  backend's `check` reports it, `qnav-robot --check` (bringup.run_check) lists it as a PROBLEM;
  once the other node is quiet for the hold time (3 s) the robot arms again.

Before the fix (commit 328bab9): 100,000 continuation frames held 18 MB for good and the end frame
stalled the receive thread 1.8-2.9 s; 50 requests put 450 answer frames ahead of the wheel command;
a collision went unnoticed.
"""

from __future__ import annotations

import random
import threading
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from firmware_py.profile import load_profile
from firmware_py.vehicle import CtrlState
from ground_station.lab.faults.common import ScenarioResult, register, trials

ROOT = Path(__file__).resolve().parents[3]
PROFILE = ROOT / "firmware_py" / "profiles" / "dronecan.toml"
PERIOD_MS = 50.0
FLOOD_FRAMES = 100_000
FRAMES_PER_TICK = 1_000
MEMORY_LIMIT = 1 << 20
FOREIGN = 42  # the flooding node's id
BUS_BITS_PER_S = 1_000_000
RPM_COMMAND_DTID = 1031  # uavcan.equipment.esc.RPMCommand
GET_NODE_INFO_DTID = 1  # uavcan.protocol.GetNodeInfo


def _rig(seed: int, goals: bool, answer_timeout_s: float = 60.0) -> Any:
    from ground_station.lab.rigs.lockstep import LockstepRig, cell_policy, far_trip, paper10

    gm, pol = paper10(), cell_policy()
    start, goal = far_trip(gm, pol, random.Random(seed))
    return LockstepRig(gm.occ, pol, start, [goal] if goals else [], robot=load_profile(PROFILE), seed=seed,
                       answer_timeout_s=answer_timeout_s)


def _runs(res: ScenarioResult, count: int, seed: int, progress: Any, first_seed: int, goals: bool,
          run: Callable[[Any, int, list[str]], dict[str, Any]]) -> list[dict[str, Any]]:
    """`count` trials `run(rig, i, problems)`, each on a fresh `_rig` (seed first_seed + i) that it
    enters, checked as `seed {seed}/{i}`; the figures it returns are res.figures["runs"] (returned)."""
    runs = []
    for i in trials(count, progress):
        problems: list[str] = []
        runs.append(run(_rig(first_seed + i, goals=goals), i, problems))
        res.check(problems, f"seed {seed}/{i}")
    res.figures["runs"] = runs
    return runs


def _backend(rig: Any) -> Any:
    drive = rig.node.drive
    return next(p for p in getattr(drive, "parts", [drive]) if hasattr(p, "engine"))


def _frames(transfer: Any) -> list[can.Message]:
    return [can.Message(arbitration_id=f.message_id, data=bytes(f.bytes), is_extended_id=True)
            for f in transfer.to_frames()]


def bus_us(frames: list[can.Message]) -> float:
    """Bus time of extended data frames at 1 Mbit/s, without bit stuffing (67 bits + 8 a byte)."""
    return sum(67 + 8 * len(f.data) for f in frames) * 1e6 / BUS_BITS_PER_S


class _TimedTake:
    """The backend's `take`, timed (the longest single frame's handling, in the node's receive thread)."""

    def __init__(self, backend: Any) -> None:
        self.backend, self.inner = backend, backend.take
        self.longest_ns = 0
        backend.take = self

    def __call__(self, msg: can.Message, now_us: int) -> Any:
        t0 = time.perf_counter_ns()
        try:
            return self.inner(msg, now_us)
        finally:
            self.longest_ns = max(self.longest_ns, time.perf_counter_ns() - t0)

    def restore(self) -> None:
        del self.backend.take


# --- reassembly flood ---------------------------------------------------------------------------

FLOOD_KINDS = ("debug.LogMessage", "unknown type id")


def flood_frames(kind: str, n: int) -> tuple[can.Message, list[can.Message], can.Message]:
    """(start frame, n continuation frames, end frame) of one transfer from node FOREIGN."""
    import dronecan
    from dronecan import transport

    log = dronecan.uavcan.protocol.debug.LogMessage(source="flood", text="x" * 60)
    tr = transport.Transfer(payload=log, source_node_id=FOREIGN, transfer_id=7, transfer_priority=24)
    first = _frames(tr)[0]
    arb = first.arbitration_id
    if kind == "unknown type id":  # a message type id no DSDL here defines
        unknown = next(d for d in range(20, 60000) if (d, 1) not in dronecan.DATATYPES)
        arb = (arb & ~(0xFFFF << 8)) | (unknown << 8)
        first = can.Message(arbitration_id=arb, data=first.data, is_extended_id=True)
    tid = first.data[-1] & 0x1F
    cont = [can.Message(arbitration_id=arb, data=bytes(7) + bytes([tid | (0x20 if k % 2 == 0 else 0)]),
                        is_extended_id=True) for k in range(n)]
    end = can.Message(arbitration_id=arb, data=bytes(3) + bytes([tid | 0x40 | (0x20 if n % 2 == 0 else 0)]),
                      is_extended_id=True)
    return first, cont, end


@register("dronecan_reassembly_flood", small=1, large=4, unit="floods of 100,000 frames",
          what="an unfinished DroneCAN transfer fed 100,000 continuation frames: < 1 MB kept, "
               "its end frame's tick and every frame's handling < 50 ms, every tick answered, no FAULT")
def reassembly_flood(res: ScenarioResult, count: int, seed: int, progress: Any, frames: int = FLOOD_FRAMES) -> None:
    runs = []
    for i in trials(count, progress):
        kind = FLOOD_KINDS[i % len(FLOOD_KINDS)]
        first, cont, end = flood_frames(kind, frames)
        problems: list[str] = []
        with _rig(seed * 7919 + 43_000 + i, goals=True) as rig:
            rig.run_until(1_000_000)
            timed = _TimedTake(_backend(rig))
            tracemalloc.start()
            try:
                rig.tick()
                base = tracemalloc.get_traced_memory()[0]
                rig.send(first)
                longest_tick_ms = 0.0
                for k in range(0, len(cont), FRAMES_PER_TICK):
                    for f in cont[k:k + FRAMES_PER_TICK]:
                        rig.send(f)
                    t0 = time.perf_counter()
                    rig.tick()  # after the frames: the receive thread took them all
                    longest_tick_ms = max(longest_tick_ms, (time.perf_counter() - t0) * 1e3)
                held = tracemalloc.get_traced_memory()[0] - base
            finally:
                tracemalloc.stop()
            flood_take_ms = timed.longest_ns / 1e6
            timed.longest_ns = 0
            rig.send(end)
            t0 = time.perf_counter()
            rig.tick()
            end_tick_ms = (time.perf_counter() - t0) * 1e3
            end_take_ms = timed.longest_ns / 1e6
            rig.run_until(rig.time_us + 500_000)
            timed.restore()
            stats = rig.node.drive.stats()
            fault = rig.first_transition_to(CtrlState.FAULT)
        run = {"kind": kind, "frames": len(cont), "held_bytes": held, "end_tick_ms": round(end_tick_ms, 2),
               "end_take_ms": round(end_take_ms, 2), "flood_take_ms": round(flood_take_ms, 2),
               "flood_tick_ms": round(longest_tick_ms, 2),
               "dropped": stats.get("dronecan_dropped_transfers"), "bad": stats.get("dronecan_bad_transfers")}
        runs.append(run)
        if held >= MEMORY_LIMIT:
            problems.append(f"{held / 1e6:.1f} MB held after {len(cont)} continuation frames")
        if end_tick_ms > PERIOD_MS or end_take_ms > PERIOD_MS:
            problems.append(f"end frame: tick {end_tick_ms:.0f} ms, its handling {end_take_ms:.0f} ms")
        if fault is not None:
            problems.append(f"FAULT: {fault.cause}")
        res.check(problems, f"seed {seed}/{i} {kind}")
    res.figures["runs"] = runs
    res.figures["held_bytes_max"] = max((r["held_bytes"] for r in runs), default=0)
    res.figures["end_tick_ms_max"] = max((r["end_tick_ms"] for r in runs), default=0.0)
    res.figures["end_take_ms_max"] = max((r["end_take_ms"] for r in runs), default=0.0)


# --- service flood ------------------------------------------------------------------------------

REQUESTS = 50


def node_info_requests(dest: int, n: int, first_source: int = 20) -> list[can.Message]:
    import dronecan
    from dronecan import transport

    out: list[can.Message] = []
    for k in range(n):
        req = dronecan.uavcan.protocol.GetNodeInfo.Request()
        tr = transport.Transfer(payload=req, source_node_id=first_source + k, dest_node_id=dest, transfer_id=k % 32,
                                transfer_priority=30, service_not_message=True, request_not_response=True)
        out += _frames(tr)
    return out


def _is_answer(f: can.Message, node_id: int) -> bool:
    i = f.arbitration_id
    return bool(f.is_extended_id and i & 0x80 and (i >> 16) & 0xFF == GET_NODE_INFO_DTID
                and not (i >> 15) & 1 and i & 0x7F == node_id)


def _is_command(f: can.Message, node_id: int) -> bool:
    i = f.arbitration_id
    return bool(f.is_extended_id and not i & 0x80 and (i >> 8) & 0xFFFF == RPM_COMMAND_DTID and i & 0x7F == node_id)


@register("dronecan_service_flood", small=2, large=20, unit="ticks with 50 GetNodeInfo requests",
          what="50 GetNodeInfo requests in one tick while driving: no answer frame ahead of the wheel "
               "command, at most one answer a tick, every requester answered later")
def service_flood(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    runs = _runs(res, count, seed, progress, seed * 7919 + 43_500, True, _service_flood_run)
    res.figures["answer_frames_ahead_max"] = max((r["answer_frames_ahead"] for r in runs), default=0)


def _service_flood_run(rig: Any, i: int, problems: list[str]) -> dict[str, Any]:
    with rig:
        node_id = _backend(rig).engine.node_id
        rig.run_until(1_500_000 + 50_000 * i)
        listener = can.Bus(interface="virtual", channel=rig.node_bus.channel_id)
        try:
            for f in node_info_requests(node_id, REQUESTS):
                rig.send(f)
            rig.tick()
            tick1 = _drain(listener)
            rest = []
            per_tick = []
            for _ in range(200):  # 10 s of ticks: the rest of the answers at the backend's rate
                rig.tick()
                got = _drain(listener)
                per_tick.append(sum(_is_answer(f, node_id) for f in got))
                rest += got
        finally:
            listener.shutdown()
        fault = rig.first_transition_to(CtrlState.FAULT)
    robot = [f for f in tick1 if f.is_extended_id and f.arbitration_id & 0x7F == node_id]
    cmd_at = next((k for k, f in enumerate(robot) if _is_command(f, node_id)), None)
    ahead = [f for f in robot[:cmd_at] if _is_answer(f, node_id)] if cmd_at is not None else []
    after = [f for f in robot[(cmd_at or 0):] if _is_answer(f, node_id)]
    answered = _answered(tick1 + rest, node_id)
    run = {"answer_frames_ahead": len(ahead), "bus_ms_ahead": round(bus_us(ahead) / 1e3, 2),
           "answer_frames_after": len(after), "max_answer_frames_later_tick": max(per_tick, default=0),
           "requesters_answered_10s": len(answered)}
    if cmd_at is None:
        problems.append("no esc.RPMCommand in the tick with the requests")
    if ahead:
        problems.append(f"{len(ahead)} answer frames ({bus_us(ahead) / 1e3:.1f} ms of the bus) ahead of the command")
    if len(after) > 9 or max(per_tick, default=0) > 9:
        problems.append(f"{max([len(after), *per_tick])} answer frames in one tick")
    if len(answered) < 10:
        problems.append(f"only {len(answered)} of {REQUESTS} requesters answered in 10 s")
    if fault is not None:
        problems.append(f"FAULT: {fault.cause}")
    return run


def _drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (m := bus.recv(timeout=0)) is not None:
        out.append(m)
    return out


def _answered(frames: list[can.Message], node_id: int) -> set[int]:
    """The requesters a complete GetNodeInfo response went to (its end frame)."""
    return {(f.arbitration_id >> 8) & 0x7F for f in frames if _is_answer(f, node_id) and f.data[-1] & 0x40}


# --- node-id collision --------------------------------------------------------------------------

HOLD_S = 3.0


def node_status_frame(node_id: int, uptime: int, tid: int) -> can.Message:
    import dronecan
    from dronecan import transport

    st = dronecan.uavcan.protocol.NodeStatus(uptime_sec=uptime, health=0, mode=0)
    tr = transport.Transfer(payload=st, source_node_id=node_id, transfer_id=tid % 32, transfer_priority=24)
    return _frames(tr)[0]


def check_lines(node_id: int, listen_s: float = 0.6) -> list[str]:
    """`qnav-robot --check`'s report (bringup.run_check) while another node sends NodeStatus with our id."""
    from firmware_py.bringup import run_check

    channel = f"dronecan-collision-{random.getrandbits(32):08x}"
    robot = can.Bus(interface="virtual", channel=channel)
    other = can.Bus(interface="virtual", channel=channel)
    stop = threading.Event()

    def beat() -> None:
        k = 0
        while not stop.wait(0.1):
            other.send(node_status_frame(node_id, k, k))
            k += 1

    t = threading.Thread(target=beat, daemon=True)
    t.start()
    try:
        rep = run_check(robot, load_profile(PROFILE), listen_s=listen_s)
    finally:
        stop.set()
        t.join()
        robot.shutdown()
        other.shutdown()
    return rep.lines


@register("dronecan_node_id_collision", small=1, large=5, unit="collisions",
          what="another node sending NodeStatus with the robot's DroneCAN node id: arming refused naming it, "
               "--check reports it; armed again once it is quiet 3 s")
def node_id_collision(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    _runs(res, count, seed, progress, seed * 7919 + 44_000, False, _collision_run)


def _collision_run(rig: Any, _i: int, problems: list[str]) -> dict[str, Any]:
    with rig:
        backend = _backend(rig)
        node_id = backend.engine.node_id
        rig.run_until(1_000_000)
        for k in range(3):  # 1 Hz, as a node's NodeStatus
            rig.send(node_status_frame(node_id, 100 + k, k))
            rig.run_until(rig.time_us + 1_000_000)
        said_events = [e.text for e in rig.ctrl.drain_events() if f"node id {node_id}" in e.text]
        if len(said_events) != 1:  # the STATUSTEXT the link sends: once, when it began
            problems.append(f"{len(said_events)} events naming the collision (one expected)")
        ok, why = rig.ctrl.arm()
        detail = str(rig.node.inputs.snapshot().__dict__.get("arm_block", ""))
        if ok:
            problems.append("armed while another node uses the robot's node id")
            rig.ctrl.disarm()
        elif f"node id {node_id}" not in why:
            problems.append(f"refused, but not naming the collision: {why!r}")
        rig.run_until(rig.time_us + int((HOLD_S + 0.5) * 1e6))  # the other node quiet
        ok_after, why_after = rig.ctrl.arm()
        if not ok_after:
            problems.append(f"still refused {HOLD_S + 0.5:.1f} s after the last colliding frame: {why_after}")
        stats = rig.node.drive.stats()
    lines = check_lines(node_id)
    said = [ln for ln in lines if ln.startswith("PROBLEM") and f"node id {node_id}" in ln]
    if not said:
        problems.append("qnav-robot --check did not report the collision")
    return {"refused": not ok, "why": why, "detail": detail, "armed_after": ok_after,
            "check_line": said[0] if said else "", "collision_frames": stats.get("dronecan_collision_frames")}


def summary(res: ScenarioResult) -> str:
    """One line for `qnav bench faults`' table."""
    f = res.figures
    if res.name == "dronecan_reassembly_flood":
        return (f"held {f.get('held_bytes_max', 0) / 1e6:.2f} MB after {FLOOD_FRAMES} frames, "
                f"end-frame tick {f.get('end_tick_ms_max', 0):.1f} ms (take {f.get('end_take_ms_max', 0):.1f} ms)")
    if res.name == "dronecan_service_flood":
        runs = f.get("runs", [])
        return (f"{f.get('answer_frames_ahead_max', 0)} answer frames ahead of the wheel command; "
                f"<= {max((r['max_answer_frames_later_tick'] for r in runs), default=0)} a later tick; "
                f"{min((r['requesters_answered_10s'] for r in runs), default=0)}/{REQUESTS} answered in 10 s")
    if res.name == "dronecan_node_id_collision":
        runs = f.get("runs", [])
        refused = sum(r["refused"] for r in runs)
        return f"arm refused {refused}/{len(runs)}, --check reported {sum(bool(r['check_line']) for r in runs)}/{len(runs)}"
    return ""
