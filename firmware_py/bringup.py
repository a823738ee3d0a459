"""`qnav-robot --check`: which boards answer on the bus, and (with --check-motors) whether each
wheel turns the way the profile says. What it reports, and how a wheel's direction is told when its
encoder counts the motor: docs/deploy.md, "5. Describe the robot, then check it".

The bus is read, and the wheels spun, through the profile's drive backend as the controller does.
`run_check` returns the report lines and whether everything needed is there; the CLI prints them
and exits 0 or 1. Wall clock; the robot must not be driving (it is not armed: the controller is
not running during a check).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can

from firmware_py import can_protocol as proto
from firmware_py import robot_spec
from firmware_py.control.io import Heartbeat, Inputs, MotorCommand, Outputs
from firmware_py.control.node import InputTracker
from firmware_py.drives import open_drive
from firmware_py.profile import RobotProfile

SPIN_MM_S = 250  # a gentle wheel speed: the 45 degrees take 0.8 s
SPIN_TURN_RAD = 0.785  # each wheel alone turns the robot about 45 degrees round the other wheel
MIN_COUNTS = 20  # odometry must move at least this much for a verdict
STATUS_NAMES = {robot_spec.RANGE_INVALID: "invalid", robot_spec.RANGE_VALID: "valid",
                robot_spec.RANGE_TOO_CLOSE: "too close", robot_spec.RANGE_TOO_FAR: "too far"}


@dataclass
class CheckReport:
    lines: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    def ok(self, text: str) -> None:
        self.lines.append(f"ok       {text}")

    def bad(self, text: str) -> None:
        self.lines.append(f"MISSING  {text}" if "not heard" in text else f"PROBLEM  {text}")
        self.problems.append(text)

    def note(self, text: str) -> None:
        self.lines.append(f"info     {text}")


class _Listener:
    """The bus read into one `Inputs` the way the robot reads it (the node's InputTracker, behind the
    profile's drive backend), with a count of what was heard."""

    def __init__(self, bus: can.BusABC, profile: RobotProfile, clock: Callable[[], float]) -> None:
        self.bus, self.profile, self.clock = bus, profile, clock
        self.drive = open_drive(profile)
        self.tracker = InputTracker(defer_stamps=False)
        self.heard: dict[str, int] = {}
        self.unknown: dict[int, int] = {}
        self.t0 = clock()

    @property
    def inputs(self) -> Inputs:
        return self.tracker.snapshot()

    def now_us(self) -> int:
        return int((self.clock() - self.t0) * 1e6)

    def pump(self, seconds: float) -> None:
        end = self.clock() + seconds
        while (left := end - self.clock()) > 0:
            msg = self.bus.recv(timeout=min(0.05, left))
            if msg is not None:
                self.take(msg)

    def take(self, msg: can.Message) -> None:
        now = self.now_us()
        updates = self.drive.take(msg, now)
        if updates is not None:
            for u in updates:
                self.tracker.update(u, now)
                if u.key:
                    self.heard[u.key] = self.heard.get(u.key, 0) + 1
            return
        try:
            name, sig = proto.decode(msg)
        except proto.ProtocolError:
            self.unknown[msg.arbitration_id] = self.unknown.get(msg.arbitration_id, 0) + 1
            return
        self.heard[name] = self.heard.get(name, 0) + 1
        self.tracker.apply(name, sig, now)

    def send_tick(self, left: int, right: int, enabled: bool, counter: int) -> None:
        hb = Heartbeat(state=0, mode=0, armed=enabled, policy_loaded=False, goal_active=False, errors=0,
                       counter=counter & 0xFF)
        out = Outputs(motor=MotorCommand(left, right, counter), heartbeat=hb, drive_enabled=enabled)
        for frame in self.drive.frames(out, self.now_us()):
            self.bus.send(frame)


def _part(lis: _Listener, attr: str) -> Any:
    """The backend (of a composite, drives.Composite) that has `attr` (an ODrive's axes, DroneCAN's escs)."""
    return next(p for p in getattr(lis.drive, "parts", [lis.drive]) if hasattr(p, attr))


def _drive_lines(lis: _Listener, rep: CheckReport) -> None:
    prof, inp = lis.profile, lis.inputs
    if prof.drive.backend == "odrive":
        for axis in _part(lis, "axes").axes:
            what = f"drive: {axis.name()}"
            if axis.hb_us is None:
                rep.bad(f"{what}: not heard (no heartbeat)")
            elif axis.error:
                rep.bad(f"{what}: state {axis.state_name()}, axis error 0x{axis.error:x}")
            elif axis.est_us is None:
                rep.bad(f"{what}: heartbeat but no encoder estimates (set encoder_msg_rate_ms)")
            else:
                rep.ok(f"{what}: state {axis.state_name()}, no error, position {axis.pos:.3f} turns")
        return
    if prof.drive.backend == "dronecan":
        for esc in _part(lis, "escs").escs:
            what = f"drive: {esc.name()}"
            if esc.t_us is None:
                rep.bad(f"{what}: not heard (no esc.Status with esc_index {esc.index})")
            elif esc.health >= 2:
                rep.bad(f"{what}: health {esc.health}")
            else:
                rep.ok(f"{what}: esc.Status {esc.rpm:.0f} rpm, health OK")
        return
    if "MotorStatus" not in lis.heard:
        rep.bad("drive: qnav motor driver (node 34): not heard (no MotorStatus)")
    else:
        st = proto.MOTOR_STATE_NAMES.get(inp.driver_state, str(inp.driver_state))
        text = f"drive: qnav motor driver (node 34): state {st}, errors 0x{inp.driver_errors:02x}"
        (rep.bad if inp.driver_errors else rep.ok)(text)
    if "EncoderCounts" not in lis.heard:
        rep.bad("drive: encoder counts (node 34): not heard")


def _sensor_lines(lis: _Listener, rep: CheckReport) -> None:
    inp = lis.inputs
    prof = lis.profile
    angles = prof.sensors.angles_deg
    n = len(angles)
    per = (n + 1) // 2  # the readings come in two halves (qnav's RangeSectors0/1; DroneCAN's as the backend groups them)
    for f in range(len(proto.RANGE_SECTORS_IDS)):
        name = f"RangeSectors{f}"
        idx = range(f * per, min(n, (f + 1) * per))
        if not idx:
            continue
        if name not in lis.heard and f"ranges{f}" not in lis.heard:
            board = ("DroneCAN rangefinders" if prof.sensors.backend == "dronecan" else "range board (node 35)")
            rep.bad(f"{board}: sensors {idx[0]}-{idx[-1]}: not heard")
            continue
        for i in idx:
            st = inp.range_status[i] if i < len(inp.range_status) else robot_spec.RANGE_INVALID
            mm = inp.ranges_mm[i] if i < len(inp.ranges_mm) else 0
            text = f"range sensor {i} at {angles[i]:g} deg: {mm} mm, {STATUS_NAMES.get(st, st)}"
            (rep.bad if st == robot_spec.RANGE_INVALID else rep.ok)(text)
    uncovered = prof.layout().uncovered()
    if uncovered:  # read as unknown (INVALID), never free
        dirs = ", ".join(f"{robot_spec.SENSOR_ANGLES_MRAD[k] * 180 / math.pi / 1000:.0f}" for k in uncovered)
        rep.note(f"{n} sensors: no sensor looks along policy sector(s) {dirs} deg (read as unknown)")
    if not prof.boards.bumper:
        rep.note("bumper board (node 36): none in the profile (boards.bumper = false)"
                 + ("; but one is heard" if "Bumper" in lis.heard else ""))
    elif "Bumper" not in lis.heard:
        rep.bad("bumper board (node 36): not heard")
    else:
        (rep.bad if inp.bumper else rep.ok)(f"bumper board (node 36): {'PRESSED' if inp.bumper else 'released'}")
    if "BatteryStatus" in lis.heard:
        rep.ok(f"power board (node 37): {inp.battery_mv / 1000:.2f} V, {inp.battery_pct} %")
    elif prof.boards.power:
        rep.bad("power board (node 37): not heard (boards.power = true)")
    else:
        rep.note("power board (node 37): not heard (optional: the battery shows as unknown)")


def _rotation_map(angles: tuple[float, ...], shift_deg: float) -> dict[int, int]:
    """{i: j}: sensor j looked, before a turn of `shift_deg` (CCW +), where sensor i looks after it."""
    out = {}
    for i, a in enumerate(angles):
        want = (a + shift_deg + 180) % 360 - 180
        j = min(range(len(angles)), key=lambda k: abs((angles[k] - want + 180) % 360 - 180))
        if abs((angles[j] - want + 180) % 360 - 180) <= 10:
            out[i] = j
    return out


def _turn_seen(before: list[int], after: list[int], angles: tuple[float, ...]) -> float | None:
    """+1..-1: how much better the range readings fit a 45-degree turn to the left (CCW, +) than one to
    the right; None when too few readings to tell (an open field, a symmetric room)."""
    fits = []
    for shift in (45.0, -45.0):
        pairs = [(after[i], before[j]) for i, j in _rotation_map(angles, shift).items()]
        if len(pairs) < 4:
            return None
        fits.append(sum(abs(x - y) for x, y in pairs) / len(pairs))
    left, right = fits
    if max(left, right) < 50:
        return None  # nothing changed: the robot did not turn, or sees nothing
    return (right - left) / max(left, right)


def _readings(inp: Inputs, max_mm: int) -> list[int]:
    return [inp.ranges_mm[i] if inp.range_status[i] == robot_spec.RANGE_VALID else max_mm
            for i in range(len(inp.ranges_mm))]


def _stop(lis: _Listener, counter: int) -> int:
    """Zero, then (odrive) IDLE, and let the readings settle; the next tick counter."""
    for _ in range(6):
        lis.send_tick(0, 0, enabled=False, counter=counter)
        counter += 1
        lis.pump(robot_spec.CONTROL_PERIOD_US / 1e6)
    return counter


def _spin(lis: _Listener, rep: CheckReport, side: int) -> None:
    """Turn one wheel forward slowly (about 45 degrees of the robot's heading, round the other wheel),
    the other held at zero; read odometry and the range sensors; then back to where it started.

    Odometry tells a wheel encoder's sign (qnav's EncoderCounts count the wheel). An ODrive's encoder
    and a DroneCAN ESC's rpm are the motor's: they count what the motor was told whatever way the
    motor is mounted, so the robot's turn is read from the range sensors instead (the readings rotate
    one sensor to the right when the left wheel drives forward)."""
    name = ("left", "right")[side]
    max_mm = lis.profile.sensors.max_range_mm
    before_enc = (lis.inputs.enc_left, lis.inputs.enc_right)
    before_rng = _readings(lis.inputs, max_mm)
    g = lis.profile.geometry
    seconds = SPIN_TURN_RAD * g.wheel_base_mm / SPIN_MM_S
    # until odometry says the wheel went the 45 degrees' worth (a loaded or slow board takes longer
    # than the nominal time), at most three times the nominal time
    want = SPIN_TURN_RAD * g.wheel_base_mm / (2 * math.pi * g.wheel_radius_mm) * g.encoder_counts_per_rev
    counter, end = 0, lis.clock() + 3 * seconds
    while lis.clock() < end:
        speeds = (SPIN_MM_S, 0) if side == 0 else (0, SPIN_MM_S)
        lis.send_tick(*speeds, enabled=True, counter=counter)
        counter += 1
        lis.pump(robot_spec.CONTROL_PERIOD_US / 1e6)
        now = (lis.inputs.enc_left, lis.inputs.enc_right)[side]
        if abs(proto.wrap_counts(now - before_enc[side])) >= want:
            break
    counter = _stop(lis, counter)
    after_enc = (lis.inputs.enc_left, lis.inputs.enc_right)
    after_rng = _readings(lis.inputs, max_mm)
    # back the way it came, so the other wheel's test starts where this one did (and the robot ends
    # where it was put)
    end = lis.clock() + 3 * seconds
    while lis.clock() < end:
        lis.send_tick(*((-SPIN_MM_S, 0) if side == 0 else (0, -SPIN_MM_S)), enabled=True, counter=counter)
        counter += 1
        lis.pump(robot_spec.CONTROL_PERIOD_US / 1e6)
        now = (lis.inputs.enc_left, lis.inputs.enc_right)[side]
        if proto.wrap_counts(now - before_enc[side]) * (1 if after_enc[side] >= before_enc[side] else -1) <= 0:
            break
    _stop(lis, counter)
    moved = [proto.wrap_counts(a - b) for a, b in zip(after_enc, before_enc, strict=True)]
    mine, other = moved[side], moved[1 - side]
    turn = _turn_seen(before_rng, after_rng, lis.profile.sensors.angles_deg)
    expected = -1.0 if side == 0 else 1.0  # left wheel forward: the robot turns right (clockwise)
    motor_encoder = lis.profile.drive.backend in ("odrive", "dronecan")  # both count the motor
    if lis.inputs.driver_detail:
        rep.bad(f"{name} wheel: {lis.inputs.driver_detail}")
        return
    if abs(mine) < MIN_COUNTS:
        rep.bad(f"{name} wheel: odometry moved {mine} counts for {SPIN_MM_S} mm/s over {seconds:.1f} s "
                "(motor not turning, or no encoder)")
        return
    if mine < 0 and not motor_encoder:
        rep.bad(f"{name} wheel: turned BACKWARDS ({mine} counts): flip drive.{name}_sign in the profile "
                "(or the motor's wiring)")
        return
    seen = ("not told by the range sensors (too open or too symmetric around the robot)" if turn is None
            else f"the range readings turned {'right' if turn < 0 else 'left'} (fit {abs(turn):.2f})")
    if turn is not None and abs(turn) >= 0.2 and turn * expected < 0:
        rep.bad(f"{name} wheel: the robot turned the WRONG way for a forward {name} wheel ({seen}): "
                f"flip drive.{name}_sign in the profile (or the motor's wiring)")
    elif motor_encoder and (turn is None or abs(turn) < 0.2):
        rep.note(f"{name} wheel: motor encoder {mine} counts; direction {seen}: check by eye")
    else:
        rep.ok(f"{name} wheel: forward, {mine} counts (the other wheel {other}); {seen}")


def run_check(bus: can.BusABC, profile: RobotProfile, *, listen_s: float = 2.0, spin: bool = False,
              clock: Callable[[], float] = time.monotonic) -> CheckReport:
    """Listen `listen_s` seconds, report every board; with `spin`, turn each wheel in turn."""
    rep = CheckReport()
    lis = _Listener(bus, profile, clock)
    rep.note(f"profile {profile.source}: drive {profile.drive.backend}, sensors {profile.sensors.backend}")
    # an odrive drive clears stale axis errors once at start (drives/odrive.py): send that tick first
    lis.send_tick(0, 0, enabled=False, counter=0)
    lis.pump(listen_s)
    _drive_lines(lis, rep)
    _sensor_lines(lis, rep)
    engines = [p.engine for p in getattr(lis.drive, "parts", [lis.drive]) if hasattr(p, "engine")]  # DroneCAN
    for node_id, (health, mode) in sorted(engines[0].nodes_seen.items()) if engines else ():
        rep.note(f"DroneCAN node {node_id}: health {('OK', 'WARNING', 'ERROR', 'CRITICAL')[health & 3]}, mode {mode}")
    for engine in engines:  # another node with the robot's node id, at any time during the check
        if engine.collision_frames:
            rep.bad(f"{engine.collision(lis.now_us() / 1e6, hold_s=float('inf'))} "
                    f"({engine.collision_frames} frames); the robot refuses to arm while it is seen")
    for fid, n in sorted(lis.unknown.items()):
        rep.note(f"unknown frame id 0x{fid:x} ({'extended' if fid > 0x7FF else 'standard'}): {n} frames")
    if spin:
        if rep.problems:
            rep.note("wheels not spun: fix the problems above first")
        else:
            for side in (0, 1):
                _spin(lis, rep, side)
    return rep
