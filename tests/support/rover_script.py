"""Test support for the monitor and report tests: a scripted rover telemetry
stream, encoded with pymavlink and delivered as a tlog file or over UDP.

The script is a fixed drive on the paper10 map (0.5 m cells): start at cell
(2,4) facing north, drive to target A (2,2) (mission item 0), stop 1.5 s,
then along a free-cell path to target B (9,0) (mission item 1), with a
1 s sensor fault on the way. Everything the robot's telemetry module sends
is produced from one `RoverScript.state(t)`, so tests can compute expected
values independently (path length, reached targets, times).
"""

from __future__ import annotations

import math
import struct
import threading
import time
from dataclasses import dataclass

from firmware_py import robot_spec
from firmware_py.mavlink.dialect import mavlink2 as mavlink
from firmware_py.mavlink.frames import LOCAL_ITEM_SCALE
from firmware_py.vehicle import Mode

CELL_M = 0.5
MAP_H = 10
START = (2, 4)
PATH_A = [(2, 4), (2, 3), (2, 2)]
PATH_B = [(2, 2), (3, 2), (4, 2), (5, 2), (6, 2), (6, 1), (6, 0), (7, 0), (8, 0), (9, 0)]
SPEED = 0.4
TURN_S = 0.5
T_ARM = 2.0
STOP_AT_A_S = 1.5
FAULT_AT = 8.0  # seconds after leaving A: 1 s of FAULT with no motion
FAULT_S = 1.0
PATH_LENGTH_M = (len(PATH_A) - 1 + len(PATH_B) - 1) * CELL_M
TELEMETRY_HZ = 10


def cell_xy(c: tuple[int, int]) -> tuple[float, float]:
    x, y = robot_spec.cell_center_mm(c[0], c[1], MAP_H, int(CELL_M * 1000))
    return x / 1000, y / 1000


@dataclass
class State:
    t: float
    x: float
    y: float
    heading: float
    speed: float
    armed: bool
    mode: int
    ctrl: int
    failsafe: bool
    action: int
    yaw_rate: float
    mission_seq: int
    goal: tuple[float, float]


def _segments(path: list[tuple[int, int]], heading0: float):
    """(kind, duration, start pose, end pose) legs: turn in place, then drive."""
    legs = []
    h = heading0
    for a, b in zip(path, path[1:], strict=False):
        pa, pb = cell_xy(a), cell_xy(b)
        hb = math.atan2(pb[1] - pa[1], pb[0] - pa[0])
        if abs(math.remainder(hb - h, 2 * math.pi)) > 1e-6:
            legs.append(("turn", TURN_S, (pa, h), (pa, hb)))
        legs.append(("drive", CELL_M / SPEED, (pa, hb), (pb, hb)))
        h = hb
    return legs


class RoverScript:
    """The scripted run; `state(t)` is the truth, `messages(t)` its telemetry."""

    def __init__(self) -> None:
        self.legs_a = _segments(PATH_A, math.pi / 2)
        self.t_reach_a = T_ARM + sum(leg[1] for leg in self.legs_a)
        h_at_a = self.legs_a[-1][3][1]
        self.legs_b = _segments(PATH_B, h_at_a)
        self.t_leave_a = self.t_reach_a + STOP_AT_A_S
        self.t_fault = self.t_leave_a + FAULT_AT
        self.t_reach_b = self.t_leave_a + sum(leg[1] for leg in self.legs_b) + FAULT_S
        self.t_end = self.t_reach_b + 2.0
        self.goal_a = cell_xy(PATH_A[-1])
        self.goal_b = cell_xy(PATH_B[-1])

    @staticmethod
    def _along(legs, tau: float):
        for kind, dur, (p0, h0), (p1, h1) in legs:
            if tau <= dur:
                f = tau / dur
                if kind == "turn":
                    dh = math.remainder(h1 - h0, 2 * math.pi)
                    return p0, h0 + f * dh, 0.0, (1 if dh > 0 else 2), dh / dur
                return ((p0[0] + f * (p1[0] - p0[0]), p0[1] + f * (p1[1] - p0[1])), h1, SPEED, 0, 0.0)
            tau -= dur
        kind, dur, (p0, h0), (p1, h1) = legs[-1]
        return p1, h1, 0.0, 0, 0.0

    def state(self, t: float) -> State:
        hold, auto = int(Mode.HOLD), int(Mode.AUTO)
        if t < T_ARM:
            p, h = cell_xy(START), math.pi / 2
            return State(t, *p, h, 0.0, False, hold, 1, False, -1, 0.0, 0, self.goal_a)
        if t < self.t_reach_a:
            p, h, v, a, w = self._along(self.legs_a, t - T_ARM)
            return State(t, *p, h, v, True, auto, 3, False, a, w, 0, self.goal_a)
        if t < self.t_leave_a:
            p, h, v, a, w = self._along(self.legs_a, 1e9)
            return State(t, *p, h, 0.0, True, auto, 3, False, 0, 0.0, 1, self.goal_b)
        if t < self.t_reach_b:
            tau = t - self.t_leave_a
            fault = self.t_fault <= t < self.t_fault + FAULT_S
            if t >= self.t_fault + FAULT_S:
                tau -= FAULT_S
            elif fault:
                tau = self.t_fault - self.t_leave_a
            p, h, v, a, w = self._along(self.legs_b, tau)
            if fault:
                return State(t, *p, h, 0.0, True, auto, 5, True, -1, 0.0, 1, self.goal_b)
            return State(t, *p, h, v, True, auto, 3, False, a, w, 1, self.goal_b)
        p, h = self.goal_b, self._along(self.legs_b, 1e9)[1]
        return State(t, *p, h, 0.0, t < self.t_reach_b + 1.0, hold, 4, False, -1, 0.0, 2, self.goal_b)

    def times(self) -> list[float]:
        n = int(self.t_end * TELEMETRY_HZ)
        return [i / TELEMETRY_HZ for i in range(n + 1)]

    def messages(self, t: float, prev: State | None) -> list:
        """Telemetry at time t (10 Hz stream; slow messages at 1 Hz)."""
        s = self.state(t)
        ms = int(round(t * 1000))
        out = []
        tick = int(round(t * TELEMETRY_HZ))
        if tick % TELEMETRY_HZ == 0 or prev is None or prev.armed != s.armed or prev.mode != s.mode \
                or prev.failsafe != s.failsafe:
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if s.armed else 0)
            status = mavlink.MAV_STATE_CRITICAL if s.failsafe else (
                mavlink.MAV_STATE_ACTIVE if s.armed else mavlink.MAV_STATE_STANDBY)
            out.append(mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_GENERIC, base, s.mode, status, 3))
        if tick % TELEMETRY_HZ == 0:
            overruns = 0 if t < self.t_fault else 2  # the fault's tick overran twice
            out.append(mavlink.MAVLink_sys_status_message(0x2000000, 0x2000000, 0x2000000, 150, 0xFFFF, -1, -1,
                                                          25, 3, 1, overruns, 0, 0))
            out.append(mavlink.MAVLink_param_value_message(b"POLICY_ID", 4242.0, mavlink.MAV_PARAM_TYPE_INT32, 3, 0))
            out.append(mavlink.MAVLink_param_value_message(b"POLICY_ID_HI", 0.0, mavlink.MAV_PARAM_TYPE_INT32, 3, 1))
            out.append(mavlink.MAVLink_param_value_message(b"POLICY_ID_LO", 4242.0, mavlink.MAV_PARAM_TYPE_INT32, 3, 2))
        ned_yaw = math.atan2(math.cos(s.heading), math.sin(s.heading))
        out.append(mavlink.MAVLink_local_position_ned_message(
            ms, s.y, s.x, 0.0, s.speed * math.sin(s.heading), s.speed * math.cos(s.heading), 0.0))
        out.append(mavlink.MAVLink_attitude_message(ms, 0.0, 0.0, ned_yaw, 0.0, 0.0, -s.yaw_rate))
        dists = [65535] * 72
        for j in range(8):
            dists[j] = 100 + 10 * j
        out.append(mavlink.MAVLink_obstacle_distance_message(
            int(t * 1e6), mavlink.MAV_DISTANCE_SENSOR_LASER, dists, 0, 2, 200, 45.0, 0.0,
            mavlink.MAV_FRAME_BODY_FRD))
        dist = math.hypot(s.goal[0] - s.x, s.goal[1] - s.y)
        bearing = math.degrees(math.atan2(s.goal[0] - s.x, s.goal[1] - s.y))
        out.append(mavlink.MAVLink_nav_controller_output_message(
            0.0, 0.0, int(round(math.degrees(ned_yaw))), int(round(bearing)), int(round(dist)), 0.0, 0.0, 0.0))
        out.append(mavlink.MAVLink_position_target_local_ned_message(
            ms, mavlink.MAV_FRAME_LOCAL_NED, 0xDF8, s.goal[1], s.goal[0], 0.0, 0, 0, 0, 0, 0, 0, 0, 0))
        out.append(mavlink.MAVLink_mission_current_message(min(s.mission_seq, 1), 2, 0, 0))
        state_index = int(s.x / CELL_M) * 10 + int(s.y / CELL_M)
        # as firmware_py/mavlink/telemetry.py names them; no Q-row without a decision
        named = [("STATE_IDX", state_index if s.action >= 0 else -1), ("ACTION", s.action), ("CTRL_ST", s.ctrl)]
        if s.action >= 0:
            named += [("Q0", 100 + state_index), ("Q1", 50), ("Q2", -20), ("Q3", -100)]
        for name, value in named:
            out.append(mavlink.MAVLink_named_value_int_message(ms, name.encode(), value))
        if prev is not None:
            if prev.mission_seq != s.mission_seq and s.mission_seq >= 1:
                out.append(mavlink.MAVLink_mission_item_reached_message(s.mission_seq - 1))
                out.append(mavlink.MAVLink_statustext_message(
                    mavlink.MAV_SEVERITY_INFO, f"Reached waypoint {s.mission_seq - 1}".encode(), 0, 0))
            if s.failsafe and not prev.failsafe:
                out.append(mavlink.MAVLink_statustext_message(
                    mavlink.MAV_SEVERITY_ERROR, b"Fault: sensor timeout", 0, 0))
            if prev.armed and not s.armed:
                out.append(mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_INFO, b"Disarmed", 0, 0))
        return out

    def stream(self):
        """(t, message) pairs for the whole run, in order."""
        prev = None
        for t in self.times():
            for m in self.messages(t, prev):
                yield t, m
            prev = self.state(t)


class _Sink:
    """File-like end of a MAVLink encoder: `MAVLink.send` writes frames here
    (send, not pack, so sequence numbers advance as on a real link)."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, buf) -> None:
        self.frames.append(bytes(buf))


def frame(mav: mavlink.MAVLink, msg) -> bytes:
    """Encode one message exactly as pymavlink sends it."""
    mav.send(msg)
    return mav.file.frames.pop()


def encoder(sysid: int = 1, compid: int = 1, key: bytes | None = None) -> mavlink.MAVLink:
    mav = mavlink.MAVLink(_Sink(), srcSystem=sysid, srcComponent=compid)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.link_id = 1
        mav.signing.timestamp = 1
    return mav


def gcs_mission_items(mav: mavlink.MAVLink, items: list[tuple[float, float]]) -> list:
    """MISSION_ITEM_INT messages as the GCS uploads them (local NED, m * LOCAL_ITEM_SCALE)."""
    return [mavlink.MAVLink_mission_item_int_message(
        1, 1, seq, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0,
        round(y * LOCAL_ITEM_SCALE), round(x * LOCAL_ITEM_SCALE), 0.0) for seq, (x, y) in enumerate(items)]


def write_tlog(path, script: RoverScript, t0: float = 1_700_000_000.0, with_gcs_items: bool = True,
               drop_types: tuple[str, ...] = ()) -> int:
    """Record the script as a .tlog (8-byte big-endian µs stamp + raw frame,
    the format mavutil's logfile writer uses), leaving out `drop_types`.
    Returns the frame count."""
    rover, gcs = encoder(1, 1), encoder(255, 190)
    n = 0
    with open(path, "wb") as f:
        def put(t: float, msg, mav) -> None:
            nonlocal n
            f.write(struct.pack(">Q", int((t0 + t) * 1e6) & ~3) + frame(mav, msg))
            n += 1
        if with_gcs_items:
            for m in gcs_mission_items(gcs, [script.goal_a, script.goal_b]):
                put(0.0, m, gcs)
        for t, m in script.stream():
            if m.get_type() not in drop_types:
                put(t, m, rover)
    return n


class UdpRover(threading.Thread):
    """Plays the script over real UDP with pymavlink (`udpout` to the
    monitor's `udpin` port), at `speed` x real time, looping forever, and
    answers COMMAND_LONG arm/disarm/hold with COMMAND_ACK and records them."""

    def __init__(self, port: int, speed: float = 1.0, script: RoverScript | None = None) -> None:
        super().__init__(daemon=True)
        from pymavlink import mavutil
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
        self.script = script or RoverScript()
        self.speed = speed
        self.commands: list[tuple[int, float, float]] = []  # (command, param1, param2)
        self.received: dict[str, int] = {}  # what the monitor sent us, by type
        self._stop_ev = threading.Event()

    def run(self) -> None:
        while not self._stop_ev.is_set():
            start = time.monotonic()
            for t, msg in self.script.stream():
                while not self._stop_ev.is_set():
                    lag = t / self.speed - (time.monotonic() - start)
                    self._serve_commands()
                    if lag <= 0:
                        break
                    time.sleep(min(lag, 0.01))
                if self._stop_ev.is_set():
                    return
                self.conn.mav.send(msg)

    def _serve_commands(self) -> None:
        while True:
            m = self.conn.recv_match(blocking=False)
            if m is None:
                return
            self.received[m.get_type()] = self.received.get(m.get_type(), 0) + 1
            if m.get_type() != "COMMAND_LONG":
                continue
            self.commands.append((m.command, m.param1, m.param2))
            self.conn.mav.command_ack_send(m.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0, m.get_srcSystem(),
                                           m.get_srcComponent())

    def stop(self) -> None:
        self._stop_ev.set()
        self.join(timeout=5)
        self.conn.close()
