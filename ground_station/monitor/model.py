"""What the ground station knows about the robot, built from MAVLink alone.

`VehicleView` is a pure model: feed it every received message with `update(msg, t)` (a decoded
pymavlink message and the receive time in seconds, wall clock live or the tlog stamp in a replay)
and read its fields. No I/O, no threads, no terminal: the textual dashboard, the `--plain` status
line and `qnav report` all read the same view, and tests drive it with pymavlink-encoded messages.

Clocks: `t` is the receive time; the robot's own time base is `robot_s` (its `time_boot_ms`; sim
time in HIL). One vehicle: the view locks onto one system id and counts frames from other systems in
`foreign`; a second process with the same id is ignored (`time_conflicts`), a reboot or a pause is
followed: the rules are in docs/monitor.md, `qnav monitor`.

Frames: MAVLink LOCAL_POSITION_NED has x north, y east; the view stores
positions in the project's world frame (`firmware_py.robot_spec`: x east, y north,
metres) and headings counter-clockwise from east (radians).
"""

from __future__ import annotations

import math
import re
from collections import deque
from dataclasses import dataclass, field

from firmware_py.mavlink import frames as mav_frames
from firmware_py.mavlink.dialect import mavlink2 as mavlink
from firmware_py.vehicle import CtrlState, Mode
from ground_station.mavlink.statustext import StatusText, StatusTextAssembler

# NAMED_VALUE_INT names the robot's telemetry uses (firmware_py/mavlink/telemetry.py):
# the controller state (CtrlState), the encoder's state index, the chosen
# action and that state's int Q-row as Q0..Qn.
NV_CTRL_STATE = "CTRL_ST"
NV_STATE_INDEX = "STATE_IDX"
NV_ACTION = "ACTION"
NV_QROW_LEN = "Q_N"  # the row's length, sent before Q0..Qn: the row is taken whole, never half-updated
_QROW_RE = re.compile(r"^Q(\d+)$")
# the robot's stall report (firmware_py.control.controller.Controller._stalled): "[item N: ]stalled: WHY, D mm to go"
_STALL_RE = re.compile(r"^(item \d+: )?stalled: ")
# POLICY_ID's exact halves: a 32-bit id does not survive the float32 of PARAM_VALUE
POLICY_ID_HALVES = ("POLICY_ID_HI", "POLICY_ID_LO")

MODE_NAMES = {m.value: m.name.capitalize() for m in Mode}
CTRL_NAMES = {s.value: s.name for s in CtrlState}
SEVERITY_NAMES = ("EMERG", "ALERT", "CRIT", "ERROR", "WARN", "NOTICE", "INFO", "DEBUG")

_GLOBAL_FRAMES = {
    mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_FRAME_GLOBAL_INT,
    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT,
    mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
}
_TRAIL_STEP_M = 0.02  # trail points closer than this add nothing visible
_TRAIL_MAX = 20_000
_LOG_MAX = 500
_SEQ_GAP_RESET = 128  # a jump this large is a reboot/reconnect, not loss
BACKWARDS_MS = 2000  # a time_boot_ms this far behind the newest is another time base
FORWARDS_MS = 10_000  # ... or this far ahead (timed telemetry comes at >= 1 Hz of robot time)
SEQ_WINDOW = 32  # with two time bases heard: an untimed frame is ours if its seq follows ours this closely
REBOOT_S = 3.0  # only the other time base heard for this long (receive time): a reboot
# ... or for this many timed frames in a row, none of ours between them: a second process
# sharing our id interleaves its frames with ours, while our own robot after lost frames
# (a starved reader in a lockstep run) is the only voice, and may finish within REBOOT_S.
REBOOT_FRAMES = 50
# A jump ahead by more than FORWARDS_MS from the very process we follow (its frame's seq is
# within this of our last one): the robot went quiet while its clock ran on, not a second process.
PAUSE_SEQ_WINDOW = 4
PAUSE_MAX_SPEEDUP = 50.0  # ... and no faster than this many robot seconds per receive second


def field_text(value: bytes | str) -> str:
    """A MAVLink char[] field (NAMED_VALUE_INT name, PARAM_VALUE param_id) as text, whichever
    pymavlink returned."""
    return value.decode() if isinstance(value, bytes) else value


def obstacle_increment_deg(msg) -> float:
    """OBSTACLE_DISTANCE's bin width in degrees: increment_f when set, else the integer increment."""
    return msg.increment_f if msg.increment_f > 0 else float(msg.increment)


def policy_id_text(policy_id: int | None) -> str:
    """A policy id as the demo, `qnav policy inspect` and the upload print it."""
    return "-" if policy_id is None else f"0x{policy_id:08x}"


@dataclass
class LinkHealth:
    """Link figures as the monitor shows them."""

    last_heartbeat_t: float | None = None
    received: int = 0  # frames from the vehicle with a sequence number
    lost: int = 0  # frames missing from sequence gaps
    signed_frames: int = 0  # frames carrying a signature block
    verified_frames: int = 0  # frames whose signature our key verified
    # the robot's own counters (SYS_STATUS, as firmware_py/mavlink/telemetry.py fills it)
    drop_rate_comm_pct: float = 0.0  # frames the robot dropped / received
    rx_dropped: int = 0  # errors_comm: signing drops + unparseable frames
    can_errors: int = 0  # errors_count1
    tick_overruns: int = 0  # errors_count2: control ticks that missed their period
    signing_dropped: int = 0  # errors_count3

    @property
    def loss_pct(self) -> float:
        total = self.received + self.lost
        return 100.0 * self.lost / total if total else 0.0

    @property
    def signing(self) -> bool:
        """The vehicle signs what it sends (last frames carried a signature)."""
        return self.signed_frames > 0


@dataclass
class Mission:
    """Mission progress as the robot reports it (and items we saw pass)."""

    current: int = -1
    total: int = 0
    state: int = 0
    reached: list[int] = field(default_factory=list)
    items: dict[int, tuple[float, float]] = field(default_factory=dict)  # seq -> world (x, y) m


@dataclass
class LogLine:
    t: float
    severity: int
    text: str
    robot_t: float | None = None  # VehicleView.robot_clock() when it arrived

    @property
    def severity_name(self) -> str:
        return SEVERITY_NAMES[self.severity] if 0 <= self.severity < len(SEVERITY_NAMES) else str(self.severity)


def _runs(bins: list[int]) -> list[tuple[int, int]]:
    """(start, length) of runs of equal known values (not UINT16_MAX) in a circular list of bins."""
    n = len(bins)
    known = [b != 65535 for b in bins]
    if not any(known):
        return []
    # start scanning at a run boundary so a run crossing index 0 stays whole
    first = next((i for i in range(n) if bins[i] != bins[i - 1] or not known[i - 1]), 0)
    runs, i = [], 0
    while i < n:
        j = (first + i) % n
        if not known[j]:
            i += 1
            continue
        length = 1
        while i + length < n and bins[(j + length) % n] == bins[j]:
            length += 1
        runs.append((j, length))
        i += length
    return runs


class VehicleView:
    """Latest known state of one vehicle (by default the first rover heard). Messages from other
    systems are ignored, except mission items addressed to it, which tell us the mission targets."""

    def __init__(self, sysid: int | None = None, trail_max: int = _TRAIL_MAX) -> None:
        self.sysid = sysid
        self.compid: int | None = None  # component of the vehicle's heartbeat (command target)
        self.t: float | None = None  # time of the last message from the vehicle
        self.t0: float | None = None
        self.link = LinkHealth()
        self._last_seq: dict[int, int] = {}  # compid -> seq
        # HEARTBEAT
        self.mode: int | None = None
        self.armed = False
        self.system_status: int | None = None
        self.load_pct: float | None = None  # SYS_STATUS
        # pose (world frame: x east, y north, metres; heading CCW from east)
        self.boot_ms_last: int | None = None  # newest time_boot_ms of any message
        # SYSTEM_TIME: the robot's wall clock (us since 1970; 0: the robot's clock is not set), None: not sent
        self.robot_unix_us: int | None = None
        self.x: float | None = None
        self.y: float | None = None
        self.vx = 0.0  # world frame m/s
        self.vy = 0.0
        self.heading: float | None = None
        self.yaw_rate = 0.0  # rad/s, CCW positive
        self.trail: deque[tuple[float, float]] = deque(maxlen=trail_max)
        self.origin_e7: tuple[int, int] | None = None
        # localisation: ESTIMATOR_STATUS, LOCAL_POSITION_NED_COV, ODOMETRY (raw dead reckoning)
        self.localised: bool | None = None  # None: the vehicle sends no estimator status
        self.localising_global = False
        self.pose_std_m: float | None = None  # 1-sigma horizontal (None: no localiser)
        self.odom_xy: tuple[float, float] | None = None  # world frame m
        # goal
        self.wp_dist_m: float | None = None  # NAV_CONTROLLER_OUTPUT (whole metres)
        self.target_bearing_deg: float | None = None  # compass, from north clockwise
        self._position_target: tuple[float, float] | None = None
        # sensors (angle CCW from heading in radians, range m or None if no reading)
        self.sectors: list[tuple[float, float | None]] = []
        self.sector_max_m: float | None = None
        # controller
        self.ctrl_state: int | None = None
        self.state_index: int | None = None
        self.action: int | None = None
        self.q_row: dict[int, int] = {}
        self._q_pending: dict[int, int] = {}  # the Q row being received (NAMED_VALUE_INT group)
        self._q_expected: int | None = None  # its length (Q_N), when the robot sends it
        self.q_row_ready = False  # the last NAMED_VALUE_INT completed a row
        self.params: dict[str, float] = {}
        self.policy_id: int | None = None
        self.mission = Mission()
        self.log: deque[LogLine] = deque(maxlen=_LOG_MAX)
        self.log_total = 0  # lines ever appended (the deque keeps the last _LOG_MAX)
        self.stalls = 0  # the robot's stall reports heard (drives it held for getting nowhere, NAV_STALL_S)
        self._texts = StatusTextAssembler()
        self.version = 0  # bumped on every accepted message (redraw-if-changed)
        # the robot's time base (see the module docstring)
        self.robot_s: float | None = None  # robot clock, seconds (continues across a reboot)
        self.robot_s0: float | None = None  # robot clock of the first timed message
        self._boot_offset_s = 0.0
        self._robot_rx_t = 0.0  # receive time of the newest timed message
        self._conflict_since: float | None = None
        self._candidate_ms: int | None = None  # newest time_boot_ms of the other time base
        self._candidate_frames = 0  # its timed frames in a row, each consistent with the one before
        # the other time base's STATUSTEXTs, logged if it turns out to be our robot after lost
        # frames (`_robot_clock` adopts it): texts are sent once, unlike telemetry
        self._candidate_seq: dict[int, int] = {}
        self._held_texts: deque = deque(maxlen=_LOG_MAX)
        self._adopted = False
        self.time_conflicts = 0  # timed frames ignored: another process with our system id
        self.reboots = 0
        self.foreign: dict[int, int] = {}  # sysid -> frames ignored from other vehicles

    # --- derived -----------------------------------------------------------
    @property
    def mode_name(self) -> str:
        if self.mode is None:
            return "-"
        return MODE_NAMES.get(self.mode, f"mode{self.mode}")

    @property
    def ctrl_name(self) -> str:
        if self.ctrl_state is None:
            return "-"
        return CTRL_NAMES.get(self.ctrl_state, f"state{self.ctrl_state}")

    @property
    def failsafe(self) -> bool:
        return self.system_status == mavlink.MAV_STATE_CRITICAL

    @property
    def speed(self) -> float:
        return math.hypot(self.vx, self.vy)

    @property
    def pose(self) -> tuple[float, float, float] | None:
        if self.x is None or self.y is None:
            return None
        return (self.x, self.y, self.heading if self.heading is not None else 0.0)

    def heartbeat_age(self, now: float) -> float | None:
        hb = self.link.last_heartbeat_t
        return None if hb is None else max(0.0, now - hb)

    @property
    def goal(self) -> tuple[float, float] | None:
        """The exact current target: the current mission item in Auto, the
        POSITION_TARGET_LOCAL_NED otherwise (each the fallback of the other)."""
        item = self.mission.items.get(self.mission.current)
        if self.mode == Mode.AUTO:
            return item if item is not None else self._position_target
        return self._position_target if self._position_target is not None else item

    def goal_estimate(self) -> tuple[float, float] | None:
        """The goal: exact if known, else from the robot's bearing/distance."""
        if self.goal is not None:
            return self.goal
        if self.x is None or self.y is None or self.wp_dist_m is None or self.target_bearing_deg is None:
            return None
        b = math.radians(self.target_bearing_deg)  # compass: east = sin, north = cos
        return (self.x + self.wp_dist_m * math.sin(b), self.y + self.wp_dist_m * math.cos(b))

    def distance_to_goal(self) -> float | None:
        if self.goal is not None and self.x is not None and self.y is not None:
            return math.hypot(self.goal[0] - self.x, self.goal[1] - self.y)
        return self.wp_dist_m

    # --- update ------------------------------------------------------------
    def update(self, msg, t: float) -> bool:
        """Fold one received message in; True if it changed the view."""
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            return False
        src = msg.get_srcSystem()
        if mtype == "MISSION_ITEM_INT" and (self.sysid is None or msg.target_system == self.sysid):
            self._mission_item(msg)
            self.version += 1
            return True
        if self.sysid is None:
            if mtype != "HEARTBEAT" or msg.type in (mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER) \
                    or msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID:
                return False
            self.sysid = src  # lock onto the first vehicle heartbeat, as mavutil does
        if src != self.sysid:
            vehicle_hb = (mtype == "HEARTBEAT" and msg.type != mavlink.MAV_TYPE_GCS
                          and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID)
            if vehicle_hb or src in self.foreign:  # another vehicle (not the GCS or a radio)
                self.foreign[src] = self.foreign.get(src, 0) + 1
            return False
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None:
            if not self._robot_clock(int(boot_ms), t, self._follows_own_seq(msg, PAUSE_SEQ_WINDOW)):
                self._candidate_seq[msg.get_srcComponent()] = msg.get_seq()
                return False
        elif self.time_conflicts and not self._follows_own_seq(msg):
            self.time_conflicts += 1  # two processes share our system id: keep to the one we follow
            cand = self._candidate_seq.get(msg.get_srcComponent())
            if (mtype == "STATUSTEXT" and self._conflict_since is not None and cand is not None
                    and 0 < (msg.get_seq() - cand) % 256 <= SEQ_WINDOW):
                self._candidate_seq[msg.get_srcComponent()] = msg.get_seq()
                self._held_texts.append((msg, t))
            return False
        if self._adopted:  # the other time base was our robot: its texts held meanwhile come first
            self._adopted = False
            for held, held_t in self._held_texts:
                self._on_statustext(held, held_t)
            self._held_texts.clear()
        self._link_stats(msg)
        self.t = t
        if self.t0 is None:
            self.t0 = t
        if mtype != "STATUSTEXT":  # as Link._collect: a text whose last chunk was lost ends when chunks stop
            self._log_texts(self._texts.flush(t))
        handler = getattr(self, "_on_" + mtype.lower(), None)
        if handler is not None:
            handler(msg, t)
        self.version += 1
        return True

    def flush_texts(self) -> None:
        """Log every chunked STATUSTEXT still waiting for a chunk: at the end of a recording."""
        if self._texts.pending():
            self._log_texts(self._texts.flush(None))
            self.version += 1

    def _robot_clock(self, boot_ms: int, t: float, next_in_seq: bool = False) -> bool:
        """Advance the robot clock; False if this frame is from another time base.
        `next_in_seq`: the frame follows ours in sequence, so a jump ahead is a pause."""
        last = self.boot_ms_last
        paused = (next_in_seq and last is not None and self._conflict_since is None
                  and last + FORWARDS_MS < boot_ms <= last + FORWARDS_MS + PAUSE_MAX_SPEEDUP * 1000 * (t - self._robot_rx_t))
        if last is not None and not last - BACKWARDS_MS <= boot_ms <= last + FORWARDS_MS and not paused:
            if self._conflict_since is None:
                self._conflict_since = t
            cand = self._candidate_ms
            steady = cand is not None and cand - BACKWARDS_MS <= boot_ms <= cand + FORWARDS_MS
            self._candidate_frames = self._candidate_frames + 1 if steady else 1
            self._candidate_ms = boot_ms
            if t - self._conflict_since < REBOOT_S and self._candidate_frames < REBOOT_FRAMES:
                self.time_conflicts += 1
                return False
            # only the new time base for REBOOT_S: the robot rebooted (or came back after an outage)
            if boot_ms < last:
                self.reboots += 1
                self._boot_offset_s += last / 1000.0
            self._adopted = True
        elif self._conflict_since is not None:  # our own time base again: the other one's texts stay out
            self._held_texts.clear()
        self._conflict_since = None
        self._candidate_ms, self._candidate_frames = None, 0
        self.boot_ms_last = boot_ms
        self.robot_s = self._boot_offset_s + boot_ms / 1000.0
        self._robot_rx_t = t
        if self.robot_s0 is None:
            self.robot_s0 = self.robot_s
        return True

    def _follows_own_seq(self, msg, window: int = SEQ_WINDOW) -> bool:
        last = self._last_seq.get(msg.get_srcComponent())
        return last is None or 0 < (msg.get_seq() - last) % 256 <= window

    def robot_clock(self, t: float | None = None) -> float | None:
        """Seconds of robot time since the first timed message; with a receive time `t`, plus the
        receive time since the newest one arrived (for messages that carry no time of their own)."""
        if self.robot_s is None or self.robot_s0 is None:
            return None
        ahead = 0.0 if t is None else max(0.0, t - self._robot_rx_t)
        return self.robot_s - self.robot_s0 + ahead

    @property
    def mission_reached_count(self) -> int:
        """Items reached: those we saw reported, or what the robot's reports imply for a monitor
        attached mid-mission (items are driven in order: reaching item k means 0..k are done;
        MISSION_CURRENT: every item before the current one, all of them once complete)."""
        implied = max(self.mission.reached) + 1 if self.mission.reached else 0
        if self.mission.state == mavlink.MISSION_STATE_COMPLETE:
            implied = self.mission.total
        elif self.mission.state in (mavlink.MISSION_STATE_ACTIVE, mavlink.MISSION_STATE_PAUSED):
            implied = max(implied, self.mission.current)
        return max(len(set(self.mission.reached)), implied)

    @property
    def mission_progress(self) -> str:
        """"N/T": item N (1-based) of T in progress, T/T when complete, -/T with no item."""
        if self.mission.total <= 0:
            return "-/0"
        if self.mission.state == mavlink.MISSION_STATE_COMPLETE:
            return f"{self.mission.total}/{self.mission.total}"
        if self.mission.current < 0:
            return f"-/{self.mission.total}"
        return f"{min(self.mission.current + 1, self.mission.total)}/{self.mission.total}"

    def _link_stats(self, msg) -> None:
        comp = msg.get_srcComponent()
        seq = msg.get_seq()
        last = self._last_seq.get(comp)
        if last is not None:
            gap = (seq - last - 1) % 256
            if gap < _SEQ_GAP_RESET:
                self.link.lost += gap
        self._last_seq[comp] = seq
        self.link.received += 1
        header = getattr(msg, "_header", None)
        if header is not None and header.incompat_flags & mavlink.MAVLINK_IFLAG_SIGNED:
            self.link.signed_frames += 1
        if msg.get_signed():
            self.link.verified_frames += 1

    def _on_heartbeat(self, msg, t: float) -> None:
        self.link.last_heartbeat_t = t
        self.compid = msg.get_srcComponent()
        self.mode = msg.custom_mode
        self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        self.system_status = msg.system_status

    def _on_system_time(self, msg, t: float) -> None:
        self.robot_unix_us = int(msg.time_unix_usec)

    def _on_sys_status(self, msg, t: float) -> None:
        self.load_pct = msg.load / 10.0
        self.link.drop_rate_comm_pct = msg.drop_rate_comm / 100.0
        self.link.rx_dropped = msg.errors_comm
        self.link.can_errors = msg.errors_count1
        self.link.tick_overruns = msg.errors_count2
        self.link.signing_dropped = msg.errors_count3

    def _on_local_position_ned(self, msg, t: float) -> None:
        self.x, self.y = float(msg.y), float(msg.x)  # NED -> east/north
        self.vx, self.vy = float(msg.vy), float(msg.vx)
        if not self.trail or math.hypot(self.trail[-1][0] - self.x, self.trail[-1][1] - self.y) >= _TRAIL_STEP_M:
            self.trail.append((self.x, self.y))

    def _on_estimator_status(self, msg, t: float) -> None:
        self.localised = bool(msg.flags & mavlink.ESTIMATOR_POS_HORIZ_ABS)
        self.localising_global = bool(msg.flags & mavlink.ESTIMATOR_CONST_POS_MODE)
        self.pose_std_m = float(msg.pos_horiz_accuracy) if msg.pos_horiz_accuracy > 0 else None

    def _on_local_position_ned_cov(self, msg, t: float) -> None:
        c = msg.covariance
        if not math.isnan(c[0]):
            self.pose_std_m = math.sqrt(max(c[0], c[9], 0.0))

    def _on_odometry(self, msg, t: float) -> None:
        if msg.estimator_type == mavlink.MAV_ESTIMATOR_TYPE_NAIVE:
            self.odom_xy = (float(msg.y), float(msg.x))  # NED -> east/north

    def _on_attitude(self, msg, t: float) -> None:
        # NED yaw is clockwise from north; world heading is CCW from east.
        self.heading = math.atan2(math.cos(msg.yaw), math.sin(msg.yaw))
        self.yaw_rate = -float(msg.yawspeed)

    def _on_gps_global_origin(self, msg, t: float) -> None:
        self.origin_e7 = (msg.latitude, msg.longitude)

    def _on_position_target_local_ned(self, msg, t: float) -> None:
        self._position_target = (float(msg.y), float(msg.x))

    def _on_nav_controller_output(self, msg, t: float) -> None:
        self.wp_dist_m = float(msg.wp_dist)
        self.target_bearing_deg = float(msg.target_bearing)

    def _on_obstacle_distance(self, msg, t: float) -> None:
        inc = obstacle_increment_deg(msg)
        if inc <= 0:
            return
        n = min(len(msg.distances), int(round(360.0 / inc)))
        bins = [msg.distances[i] for i in range(n)]
        sectors = []
        # One sensor fills the consecutive bins inside its field of view with
        # one value: each such run (wrapping past 360°) is one sector.
        for start, length in _runs(bins):
            d = bins[start]
            angle_cw = math.radians(msg.angle_offset + (start + (length - 1) / 2) * inc)  # BODY_FRD: clockwise
            angle = math.atan2(-math.sin(angle_cw), math.cos(angle_cw))
            if angle < -math.pi + 1e-9:  # straight back is +180°, not -180°
                angle = math.pi
            rng = None if d > msg.max_distance or d < msg.min_distance else d / 100.0  # None: nothing in range
            sectors.append((angle, rng))
        self.sectors = sectors
        self.sector_max_m = msg.max_distance / 100.0

    def _on_mission_current(self, msg, t: float) -> None:
        self.mission.current = msg.seq
        self.mission.total = msg.total
        self.mission.state = msg.mission_state

    def _on_mission_item_reached(self, msg, t: float) -> None:
        self.mission.reached.append(msg.seq)

    def _on_mission_count(self, msg, t: float) -> None:
        self.mission.total = msg.count

    def _mission_item(self, msg) -> None:
        if msg.frame == mavlink.MAV_FRAME_LOCAL_NED:
            self.mission.items[msg.seq] = (msg.y / mav_frames.LOCAL_ITEM_SCALE, msg.x / mav_frames.LOCAL_ITEM_SCALE)
        elif msg.frame in _GLOBAL_FRAMES and self.origin_e7 is not None:
            x_mm, y_mm = mav_frames.global_to_world(msg.x, msg.y, *self.origin_e7)
            self.mission.items[msg.seq] = (x_mm / 1000, y_mm / 1000)

    def _on_named_value_int(self, msg, t: float) -> None:
        name = field_text(msg.name)
        self.q_row_ready = False
        if name == NV_STATE_INDEX:  # a new group
            self._q_pending, self._q_expected = {}, None
            self.state_index = msg.value
            if msg.value < 0:  # no policy decision: no row (the robot stops sending Qn)
                self.q_row = {}
        elif name == NV_ACTION:
            self.action = msg.value
        elif name == NV_CTRL_STATE:
            self.ctrl_state = msg.value
        elif name == NV_QROW_LEN:
            self._q_expected = msg.value
            if msg.value <= 0:
                self._commit_q_row()
        else:
            m = _QROW_RE.match(name)
            expected = self._q_expected
            if m and expected is None:  # a robot without Q_N: value by value, as it comes
                self.q_row[int(m.group(1))] = msg.value
                self.q_row_ready = True
            elif m:
                self._q_pending[int(m.group(1))] = msg.value
                if expected is not None and len(self._q_pending) >= expected:
                    self._commit_q_row()

    def _commit_q_row(self) -> None:
        self.q_row, self._q_pending = self._q_pending, {}
        self.q_row_ready = True

    def _on_param_value(self, msg, t: float) -> None:
        pid = field_text(msg.param_id)
        self.params[pid] = msg.param_value
        hi, lo = (self.params.get(n) for n in POLICY_ID_HALVES)
        if pid in POLICY_ID_HALVES and hi is not None and lo is not None:
            self.policy_id = (int(hi) << 16) | int(lo)

    def _on_statustext(self, msg, t: float) -> None:
        self._log_texts(self._texts.add(msg, t))

    def _log_texts(self, texts: list[StatusText]) -> None:
        for st in texts:
            self._append_log(LogLine(st.t, st.severity, st.text, self.robot_clock()))
            self.stalls += bool(_STALL_RE.match(st.text))

    def _append_log(self, line: LogLine) -> None:
        self.log.append(line)
        self.log_total += 1

    def _on_command_ack(self, msg, t: float) -> None:
        try:
            cmd = mavlink.enums["MAV_CMD"][msg.command].name.removeprefix("MAV_CMD_")
            res = mavlink.enums["MAV_RESULT"][msg.result].name.removeprefix("MAV_RESULT_")
        except KeyError:
            cmd, res = str(msg.command), str(msg.result)
        self._append_log(LogLine(t, mavlink.MAV_SEVERITY_INFO if msg.result == 0 else mavlink.MAV_SEVERITY_WARNING,
                                 f"ACK {cmd}: {res}", self.robot_clock()))

    @property
    def localisation_text(self) -> str:
        """`localised=yes std=0.03m odo_err=0.42m` (odo_err: believed - dead reckoning)."""
        if self.localised is None:
            return "localised=-"
        state = "global" if self.localising_global else ("yes" if self.localised else "no")
        if self.localised and self.pose_std_m is None:
            state = "off"  # no map on the robot: odometry only
        out = f"localised={state}"
        if self.pose_std_m is not None:
            out += f" std={self.pose_std_m:.2f}m"
        if self.odom_xy is not None and self.x is not None and self.y is not None:
            out += f" odo_err={math.hypot(self.odom_xy[0] - self.x, self.odom_xy[1] - self.y):.2f}m"
        return out

    # --- presentation helpers ---------------------------------------------
    def status_line(self, now: float) -> str:
        """One line for logs (`qnav monitor --plain`)."""
        age = self.heartbeat_age(now)
        pose = self.pose
        pose_s = f"x={pose[0]:.2f} y={pose[1]:.2f} hdg={round(math.degrees(pose[2])):d}" if pose else "pose=-"
        d = self.distance_to_goal()
        q = ",".join(str(self.q_row[k]) for k in sorted(self.q_row)) if self.q_row else "-"
        parts = [
            f"hb_age={age:.1f}s" if age is not None else "hb_age=-",
            f"loss={self.link.loss_pct:.1f}%",
            f"signed={'yes' if self.link.signing else 'no'}",
            f"mode={self.mode_name}",
            f"armed={'yes' if self.armed else 'no'}",
            f"ctrl={self.ctrl_name}",
            f"failsafe={'yes' if self.failsafe else 'no'}",
            f"policy={policy_id_text(self.policy_id)}",
            pose_s,
            self.localisation_text,
            f"goal_dist={d:.2f}" if d is not None else "goal_dist=-",
            f"state={self.state_index if self.state_index is not None and self.state_index >= 0 else '-'}",
            f"action={self.action if self.action is not None and self.action >= 0 else '-'}",
            f"q=[{q}]",
            f"mission={self.mission_progress} reached={self.mission_reached_count}",
            f"stalls={self.stalls}",
        ]
        return " ".join(parts)
