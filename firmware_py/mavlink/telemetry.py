"""Telemetry: what the robot streams, how often, and how each message is built.

Owns the per-message interval table (defaults from params, changed by MAV_CMD_SET_MESSAGE_INTERVAL,
one-shot by MAV_CMD_REQUEST_MESSAGE), the builders that turn a `VehicleStatus` into MAVLink messages
in the frames stock ground stations expect (LOCAL_NED, global around the configured origin, BODY_FRD
obstacle sectors), and the translation of vehicle events into STATUSTEXT / MISSION_ITEM_REACHED. A
pure engine: `due(now_us, ...)` returns the messages to send; the node shell sends them.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from firmware_py import robot_spec
from firmware_py.mavlink import extra
from firmware_py.mavlink import frames as mav_frames
from firmware_py.mavlink.dialect import mavlink2
from firmware_py.mavlink.metadata import GENERAL_FILE, uri
from firmware_py.mavlink.params import ParamStore
from firmware_py.vehicle import CtrlState, Mode, VehicleEvent, VehicleStatus

M = mavlink2
UINT16_MAX = 0xFFFF
INT16_MAX = 0x7FFF  # BATTERY_STATUS.temperature: unknown
OBSTACLE_SECTORS = 72
OBSTACLE_INCREMENT_DEG = 5
STATUSTEXT_LEN = 50
MIN_INTERVAL_US = 10_000
ORIGIN_INTERVAL_US = 5_000_000  # GPS_GLOBAL_ORIGIN, HOME_POSITION between the prompt sends below
LINK_QUIET_US = 2_000_000  # a frame after this much silence: a ground station (re)appeared (robot clock)
ORIGIN_PARAMS = ("ORIGIN_LAT", "ORIGIN_LON", "ORIGIN_ALT_MM")

# message id -> stream group; the group's rate comes from params or is fixed
STREAMS: dict[int, str] = {
    M.MAVLINK_MSG_ID_HEARTBEAT: "1hz",
    M.MAVLINK_MSG_ID_SYS_STATUS: "1hz",
    M.MAVLINK_MSG_ID_CURRENT_MODE: "1hz",  # Standard Modes (below)
    M.MAVLINK_MSG_ID_BATTERY_STATUS: "1hz",  # only once the power board was heard (BatteryStatus frame)
    # the robot's two clocks: time_boot_ms (its control clock, sim time in HIL) and its wall clock
    M.MAVLINK_MSG_ID_SYSTEM_TIME: "1hz",
    M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: "pos",
    M.MAVLINK_MSG_ID_ATTITUDE: "pos",
    M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: "pos",
    M.MAVLINK_MSG_ID_NAV_CONTROLLER_OUTPUT: "nav",
    M.MAVLINK_MSG_ID_OBSTACLE_DISTANCE: "nav",
    M.MAVLINK_MSG_ID_MISSION_CURRENT: "nav",
    M.MAVLINK_MSG_ID_NAMED_VALUE_INT: "nav",
    M.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: "nav",
    # ground speed and compass heading, the HUD every ground station draws (QGC, Mission Planner, MAVProxy)
    M.MAVLINK_MSG_ID_VFR_HUD: "nav",
    # the geodetic origin (ORIGIN_LAT/LON/ALT_MM; home = origin) every ORIGIN_INTERVAL_US, and at
    # once when the link comes alive (a GCS appears) or the origin changes: see `due`
    M.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: "origin",
    M.MAVLINK_MSG_ID_HOME_POSITION: "origin",
    # localisation (`localisation` below), at 1 Hz: COV and ODOMETRY are large frames that would crowd
    # a radio link at TELEM_POS_HZ; a ground station that wants them faster asks with SET_MESSAGE_INTERVAL.
    M.MAVLINK_MSG_ID_ESTIMATOR_STATUS: "1hz",
    M.MAVLINK_MSG_ID_LOCAL_POSITION_NED_COV: "1hz",
    M.MAVLINK_MSG_ID_ODOMETRY: "1hz",
}
# only on request (REQUEST_MESSAGE), never streamed by default
MSG_ID_PROTOCOL_VERSION = 300  # not in pymavlink's dialects: firmware_py/mavlink/extra.py
MSG_ID_COMPONENT_METADATA = 397
ON_REQUEST = frozenset({M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, M.MAVLINK_MSG_ID_AVAILABLE_MODES,
                        M.MAVLINK_MSG_ID_AVAILABLE_MODES_MONITOR, MSG_ID_PROTOCOL_VERSION,
                        MSG_ID_COMPONENT_METADATA})

# MAVLink's Standard Modes (QGroundControl's mode menu for a generic autopilot): each mode in HEARTBEAT
# custom_mode numbering, its MAV_STANDARD_MODE or its name (docs/mavlink.md, "Messages sent")
STANDARD_MODES: tuple[tuple[Mode, int, str], ...] = (
    (Mode.MANUAL, M.MAV_STANDARD_MODE_NON_STANDARD, "Manual"),
    (Mode.HOLD, M.MAV_STANDARD_MODE_POSITION_HOLD, ""),
    (Mode.AUTO, M.MAV_STANDARD_MODE_MISSION, ""),
    (Mode.GUIDED, M.MAV_STANDARD_MODE_NON_STANDARD, "Guided"),
)
STANDARD_OF = {mode: std for mode, std, _ in STANDARD_MODES}

CAPABILITIES = (
    M.MAV_PROTOCOL_CAPABILITY_MISSION_INT | M.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT | M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
    | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT | M.MAV_PROTOCOL_CAPABILITY_FTP
    | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED | M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)
# What the HEARTBEAT says the autopilot is: stock clients pick the PARAM_VALUE encoding and the mode
# names from it, so "ardupilot" adds MAVSDK (why: docs/mavlink.md, "Stock clients")
AUTOPILOTS = {"generic": M.MAV_AUTOPILOT_GENERIC, "ardupilot": M.MAV_AUTOPILOT_ARDUPILOTMEGA}
DEFAULT_AUTOPILOT = "generic"
FLIGHT_SW_VERSION = (0 << 24) | (1 << 16) | (0 << 8) | 255  # 0.1.0 official

SENSOR_PRESENT = (M.MAV_SYS_STATUS_SENSOR_PROXIMITY | M.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
                  | M.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL)
# No fence: present and enabled stay clear, and the health bit is set as ArduPilot
# does without a fence (a clear health bit reads as "fence breach" in MAVProxy).
HEALTHY_ABSENT = M.MAV_SYS_STATUS_GEOFENCE
# A wall clock before this (2020-01-01) was never set (no RTC/NTP): SYSTEM_TIME then
# says time_unix_usec = 0, "unknown", as the message's definition asks.
WALL_CLOCK_SET_AFTER_US = 1_577_836_800_000_000


def wall_clock_us() -> int:
    """The host's wall clock in us since 1970 (SYSTEM_TIME sends 0 for one never set: `build`)."""
    return int(time.time() * 1_000_000)


@dataclass
class NodeStats:
    """Link-side numbers the node adds to SYS_STATUS."""

    load_permille: int = 0
    rx_dropped: int = 0  # signing drops + unparseable frames
    rx_total: int = 0
    signing_dropped: int = 0


def _wrap_deg(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


class Telemetry:
    """Interval table + message builders."""

    def __init__(self, mav: mavlink2.MAVLink, params: ParamStore,
                 wall_us: Callable[[], int] = wall_clock_us) -> None:
        self.mav = mav
        self.params = params
        self.wall_us = wall_us  # SYSTEM_TIME.time_unix_usec; injected so tests can pin it
        self._override: dict[int, int] = {}  # msg id -> interval us (-1 off)
        self._next_due: dict[int, int] = {}
        self._statustext_id = 0
        self.last_reached = -1
        self.autopilot = int(AUTOPILOTS[DEFAULT_AUTOPILOT])  # HEARTBEAT.autopilot
        self.uid = 0  # AUTOPILOT_VERSION.uid: the robot's own, kept in its storage (node.boot)
        self.metadata_crc = 0  # COMPONENT_METADATA: the general metadata file's CRC (0: none served)
        # origin announcements (`due`): the receive count last seen, when it last grew, the origin last sent
        self._rx_seen = 0
        self._rx_heard_us: int | None = None
        self._origin_sent: tuple[int, ...] | None = None

    # --- intervals ----------------------------------------------------------------
    def default_interval_us(self, msg_id: int) -> int:
        """Default interval in us; 0 means not streamed."""
        group = STREAMS.get(msg_id)
        if group == "1hz":
            return 1_000_000
        if group == "origin":
            return ORIGIN_INTERVAL_US
        if group in ("pos", "nav"):
            hz = self.params.get("TELEM_POS_HZ" if group == "pos" else "TELEM_NAV_HZ")
            return 1_000_000 // hz if hz > 0 else 0
        return 0

    def interval_us(self, msg_id: int) -> int:
        """Current interval (us); 0 = not streamed."""
        override = self._override.get(msg_id)
        if override is None:
            return self.default_interval_us(msg_id)
        return 0 if override < 0 else override

    def set_interval(self, msg_id: int, interval_us: int) -> tuple[bool, str]:
        """SET_MESSAGE_INTERVAL semantics: -1 off, 0 default, >0 interval."""
        if msg_id not in STREAMS:
            return False, f"message {msg_id} cannot be streamed"
        if interval_us == 0:
            self._override.pop(msg_id, None)
        elif interval_us < 0:
            self._override[msg_id] = -1
        elif interval_us < MIN_INTERVAL_US:
            return False, f"interval {interval_us} us below {MIN_INTERVAL_US} us"
        else:
            self._override[msg_id] = int(interval_us)
        self._next_due.pop(msg_id, None)
        return True, ""

    def reset_intervals(self) -> None:
        self._override.clear()
        self._next_due.clear()

    def announce_origin(self) -> None:
        """GPS_GLOBAL_ORIGIN and HOME_POSITION due now (a new ground station was heard)."""
        for msg_id in (M.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, M.MAVLINK_MSG_ID_HOME_POSITION):
            self._next_due.pop(msg_id, None)

    def announce_origin_if_new(self, now_us: int, stats: NodeStats) -> None:
        """Make GPS_GLOBAL_ORIGIN and HOME_POSITION due now (if streamed) when a
        ground station appears (the first frame after boot or after LINK_QUIET_US
        of silence) or the origin changed, as ArduPilot sends home when it is set:
        a GCS that connects places the robot on its map at once."""
        origin = tuple(self.params.get(name) for name in ORIGIN_PARAMS)
        appeared = False
        if stats.rx_total != self._rx_seen:
            appeared = self._rx_heard_us is None or now_us - self._rx_heard_us >= LINK_QUIET_US
            self._rx_seen, self._rx_heard_us = stats.rx_total, now_us
        if appeared or origin != self._origin_sent:
            self.announce_origin()  # due now; the interval restarts from here
        self._origin_sent = origin

    def due(self, now_us: int, status: VehicleStatus, stats: NodeStats) -> list[mavlink2.MAVLink_message]:
        """Messages whose interval has elapsed (catch-up skips, no bursts)."""
        self.announce_origin_if_new(now_us, stats)
        out: list[mavlink2.MAVLink_message] = []
        for msg_id in STREAMS:
            interval = self.interval_us(msg_id)
            if interval <= 0:
                continue
            next_due = self._next_due.get(msg_id, now_us)
            if now_us < next_due:
                continue
            self._next_due[msg_id] = max(next_due + interval, now_us + interval // 2)
            out.extend(self.build(msg_id, now_us, status, stats))
        return out

    # --- builders -------------------------------------------------------------------
    def can_build(self, msg_id: int) -> bool:
        return msg_id in STREAMS or msg_id in ON_REQUEST

    def build(self, msg_id: int, now_us: int, st: VehicleStatus, stats: NodeStats) -> list[mavlink2.MAVLink_message]:
        """All instances of message `msg_id` for this status (may be empty)."""
        ms = (now_us // 1000) & 0xFFFFFFFF
        p = self.params.get
        m = self.mav
        if msg_id == M.MAVLINK_MSG_ID_HEARTBEAT:
            return [self.heartbeat(st)]
        if msg_id == M.MAVLINK_MSG_ID_SYS_STATUS:
            health = HEALTHY_ABSENT
            if st.sensors_healthy:
                health |= M.MAV_SYS_STATUS_SENSOR_PROXIMITY
            if st.motors_healthy:
                health |= M.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
            if st.state != CtrlState.FAULT:
                health |= M.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
            drop_rate = 0 if stats.rx_total == 0 else min(10_000, stats.rx_dropped * 10_000 // stats.rx_total)
            known = st.battery_pct >= 0
            return [m.sys_status_encode(
                SENSOR_PRESENT, SENSOR_PRESENT, health, min(1000, stats.load_permille),
                min(UINT16_MAX - 1, st.battery_mv) if known else UINT16_MAX,
                max(-32767, min(32767, st.battery_ma // 10)) if known else -1,
                st.battery_pct if known else -1, drop_rate, min(UINT16_MAX, stats.rx_dropped),
                min(UINT16_MAX, st.can_errors), min(UINT16_MAX, st.tick_overruns),
                min(UINT16_MAX, stats.signing_dropped), 0)]
        if msg_id == M.MAVLINK_MSG_ID_SYSTEM_TIME:
            wall = self.wall_us()
            return [m.system_time_encode(wall if wall >= WALL_CLOCK_SET_AFTER_US else 0, ms)]
        north, east = mav_frames.world_to_ned_m(st.x_mm, st.y_mm)
        heading = st.heading_mrad / 1000.0
        v_north = st.speed_mm_s * math.sin(heading) / 1000.0
        v_east = st.speed_mm_s * math.cos(heading) / 1000.0
        yaw = mav_frames.heading_to_yaw(st.heading_mrad)
        if msg_id == M.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            return [m.local_position_ned_encode(ms, north, east, 0.0, v_north, v_east, 0.0)]
        if msg_id == M.MAVLINK_MSG_ID_ATTITUDE:
            return [m.attitude_encode(ms, 0.0, 0.0, yaw, 0.0, 0.0, -st.yaw_rate_mrad_s / 1000.0)]
        if msg_id == M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            lat, lon = mav_frames.world_to_global(st.x_mm, st.y_mm, p("ORIGIN_LAT"), p("ORIGIN_LON"))
            hdg = round(math.degrees(yaw) * 100) % 36000
            return [m.global_position_int_encode(ms, lat, lon, p("ORIGIN_ALT_MM"), 0,
                                                 round(v_north * 100), round(v_east * 100), 0, hdg)]
        if msg_id == M.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            return [m.gps_global_origin_encode(p("ORIGIN_LAT"), p("ORIGIN_LON"), p("ORIGIN_ALT_MM"), now_us)]
        if msg_id == M.MAVLINK_MSG_ID_HOME_POSITION:
            return [m.home_position_encode(p("ORIGIN_LAT"), p("ORIGIN_LON"), p("ORIGIN_ALT_MM"),
                                           0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, now_us)]
        if msg_id == M.MAVLINK_MSG_ID_OBSTACLE_DISTANCE:
            return [self.obstacle_distance(now_us, st)]
        if msg_id == M.MAVLINK_MSG_ID_NAV_CONTROLLER_OUTPUT:
            if st.goal_mm is None:
                bearing_deg, dist_m = 0, 0
            else:
                bearing_deg = round(_wrap_deg(math.degrees(yaw - st.bearing_to_goal_mrad / 1000.0)))
                dist_m = min(UINT16_MAX, round(st.distance_to_goal_mm / 1000))
            return [m.nav_controller_output_encode(0.0, 0.0, bearing_deg, bearing_deg, dist_m, 0.0, 0.0, 0.0)]
        if msg_id == M.MAVLINK_MSG_ID_MISSION_CURRENT:
            return [m.mission_current_encode(min(st.mission_seq, UINT16_MAX), st.mission_count,
                                             self.mission_state(st), 0)]
        if msg_id == M.MAVLINK_MSG_ID_NAMED_VALUE_INT:
            # Q0..Qn: the current state's int Q-row, for the monitor's policy panel; Q_N (its length) first,
            # so a reader knows when the group is whole and never shows a half-updated row
            named = [(b"STATE_IDX", st.state_index), (b"ACTION", st.action), (b"CTRL_ST", int(st.state)),
                     (b"Q_N", len(st.q_row))] + [(f"Q{i}".encode(), int(q)) for i, q in enumerate(st.q_row)]
            return [m.named_value_int_encode(ms, name, value) for name, value in named]
        if msg_id == M.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED:
            return [] if st.goal_mm is None else [self.position_target(ms, *st.goal_mm)]
        if msg_id in (M.MAVLINK_MSG_ID_ESTIMATOR_STATUS, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED_COV,
                      M.MAVLINK_MSG_ID_ODOMETRY):
            return [self.localisation(msg_id, now_us, st)]
        if msg_id == M.MAVLINK_MSG_ID_BATTERY_STATUS:
            if st.battery_pct < 0:
                return []  # no power board heard: nothing to report (SYS_STATUS says unknown)
            cells = [min(UINT16_MAX - 1, st.battery_mv)] + [UINT16_MAX] * 9  # pack voltage in cell 0
            return [m.battery_status_encode(0, M.MAV_BATTERY_FUNCTION_ALL, M.MAV_BATTERY_TYPE_LIPO, INT16_MAX,
                                            cells, max(-32767, min(32767, st.battery_ma // 10)), -1, -1,
                                            st.battery_pct)]
        if msg_id == MSG_ID_PROTOCOL_VERSION:  # MAVLink 2 only (version 2.0: 200)
            return [extra.module().MAVLink_protocol_version_message(200, 200, 200, [0] * 8, [0] * 8)]
        if msg_id == MSG_ID_COMPONENT_METADATA:  # none without a storage (no FTP server to serve it)
            if not self.metadata_crc:
                return []
            return [extra.module().MAVLink_component_metadata_message(ms, self.metadata_crc, uri(GENERAL_FILE).encode())]
        if msg_id == M.MAVLINK_MSG_ID_AVAILABLE_MODES:
            return [m.available_modes_encode(len(STANDARD_MODES), i, std, int(mode), 0, name.encode())
                    for i, (mode, std, name) in enumerate(STANDARD_MODES, start=1)]
        if msg_id == M.MAVLINK_MSG_ID_AVAILABLE_MODES_MONITOR:
            return [m.available_modes_monitor_encode(0)]
        if msg_id == M.MAVLINK_MSG_ID_CURRENT_MODE:
            return [m.current_mode_encode(STANDARD_OF.get(st.mode, M.MAV_STANDARD_MODE_NON_STANDARD),
                                          int(st.mode), int(st.mode))]
        if msg_id == M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return [m.autopilot_version_encode(CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0,
                                               [0] * 8, [0] * 8, [0] * 8, 0, 0, self.uid)]
        if msg_id == M.MAVLINK_MSG_ID_VFR_HUD:
            speed = st.speed_mm_s / 1000.0
            compass = round(90 - math.degrees(st.heading_mrad / 1000.0)) % 360  # north 0, clockwise
            limit = max(1, self.params.get("MAX_WHEEL_SPD"))
            throttle = min(100, round(100 * abs(st.speed_mm_s) / limit))
            return [m.vfr_hud_encode(speed, speed, compass, throttle, p("ORIGIN_ALT_MM") / 1000.0, 0.0)]
        return []

    def localisation(self, msg_id: int, now_us: int, st: VehicleStatus) -> mavlink2.MAVLink_message:
        """ESTIMATOR_STATUS (flags: ESTIMATOR_POS_HORIZ_ABS while localised on the map;
        pos_horiz_accuracy: 1-sigma in m), LOCAL_POSITION_NED_COV (the believed pose and its
        north/east variances; the message has no heading slot; NaN first element: no localiser) or
        ODOMETRY (the raw dead-reckoning pose)."""
        m = self.mav
        std_n, std_e = st.pose_std_mm[1] / 1000.0, st.pose_std_mm[0] / 1000.0  # y north, x east
        if msg_id == M.MAVLINK_MSG_ID_ESTIMATOR_STATUS:
            flags = M.ESTIMATOR_ATTITUDE | M.ESTIMATOR_POS_HORIZ_REL
            if st.localiser != "off" and st.localised:
                flags |= M.ESTIMATOR_POS_HORIZ_ABS
            if st.localiser == "global":
                flags |= M.ESTIMATOR_CONST_POS_MODE  # the pose is not known yet
            acc = max(std_n, std_e) if st.localiser != "off" else 0.0
            return m.estimator_status_encode(now_us, flags, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, acc, 0.0)
        if msg_id == M.MAVLINK_MSG_ID_LOCAL_POSITION_NED_COV:
            north, east = mav_frames.world_to_ned_m(st.x_mm, st.y_mm)
            cov = [0.0] * 45
            if st.localiser == "off":
                cov[0] = math.nan
            else:
                # upper triangle of (x, y, z, vx, vy, vz, ax, ay, az); the heading variance has no slot
                cov[0], cov[9] = std_n * std_n, std_e * std_e
            return m.local_position_ned_cov_encode(now_us, M.MAV_ESTIMATOR_TYPE_AUTOPILOT, north, east, 0.0,
                                                   0.0, 0.0, 0.0, 0.0, 0.0, 0.0, cov)
        north, east = mav_frames.world_to_ned_m(st.odom_x_mm, st.odom_y_mm)
        yaw = mav_frames.heading_to_yaw(st.odom_heading_mrad)
        q = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
        return m.odometry_encode(now_us, M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_BODY_FRD, north, east, 0.0, q,
                                 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, [math.nan] + [0.0] * 20, [math.nan] + [0.0] * 20,
                                 0, M.MAV_ESTIMATOR_TYPE_NAIVE, 0)

    def heartbeat(self, st: VehicleStatus) -> mavlink2.MAVLink_message:
        base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if st.armed:
            base |= M.MAV_MODE_FLAG_SAFETY_ARMED
        if st.mode == Mode.GUIDED:
            base |= M.MAV_MODE_FLAG_GUIDED_ENABLED
        if st.mode == Mode.AUTO:
            base |= M.MAV_MODE_FLAG_AUTO_ENABLED | M.MAV_MODE_FLAG_GUIDED_ENABLED
        if st.failsafe or st.state == CtrlState.FAULT or st.estop:
            system_status = M.MAV_STATE_CRITICAL
        elif st.state == CtrlState.BOOT:
            system_status = M.MAV_STATE_BOOT
        elif st.armed:
            system_status = M.MAV_STATE_ACTIVE
        else:
            system_status = M.MAV_STATE_STANDBY
        return self.mav.heartbeat_encode(M.MAV_TYPE_GROUND_ROVER, self.autopilot,
                                         base, int(st.mode), system_status)

    def obstacle_distance(self, now_us: int, st: VehicleStatus) -> mavlink2.MAVLink_message:
        """Sector ranges in BODY_FRD: 72 bins of 5 deg clockwise from the nose;
        each sensor fills the bins inside its field of view, at its angle (the robot profile's:
        `VehicleStatus.range_angles_mrad`, in the readings' order)."""
        min_cm, max_cm = robot_spec.RANGE_MIN_MM // 10, st.range_max_mm // 10
        bins = [UINT16_MAX] * OBSTACLE_SECTORS
        half_fov = math.degrees(robot_spec.SENSOR_FOV_MRAD / 1000.0) / 2
        for angle_mrad, rng, status in zip(st.range_angles_mrad, st.ranges_mm, st.range_status, strict=False):
            if status == robot_spec.RANGE_VALID:
                value = max(min_cm, min(max_cm, rng // 10))
            elif status == robot_spec.RANGE_TOO_FAR:
                value = max_cm + 1
            elif status == robot_spec.RANGE_TOO_CLOSE:
                value = min_cm
            else:
                continue
            frd = (-math.degrees(angle_mrad / 1000.0)) % 360.0  # CCW from nose -> clockwise
            for i in range(OBSTACLE_SECTORS):
                centre = i * OBSTACLE_INCREMENT_DEG
                if abs(_wrap_deg(centre - frd)) <= max(half_fov, OBSTACLE_INCREMENT_DEG / 2):
                    bins[i] = value
        return self.mav.obstacle_distance_encode(
            now_us, M.MAV_DISTANCE_SENSOR_LASER, bins, OBSTACLE_INCREMENT_DEG, min_cm, max_cm,
            float(OBSTACLE_INCREMENT_DEG), 0.0, M.MAV_FRAME_BODY_FRD)

    def position_target(self, ms: int, x_mm: int, y_mm: int) -> mavlink2.MAVLink_message:
        north, east = mav_frames.world_to_ned_m(x_mm, y_mm)
        mask = 0xFFF8  # position only (x, y, z valid)
        return self.mav.position_target_local_ned_encode(
            ms, M.MAV_FRAME_LOCAL_NED, mask, north, east, 0.0, 0, 0, 0, 0, 0, 0, 0, 0)

    def mission_state(self, st: VehicleStatus) -> int:
        if st.mission_count == 0:
            return int(M.MISSION_STATE_NO_MISSION)
        if self.last_reached >= st.mission_count - 1:
            return int(M.MISSION_STATE_COMPLETE)
        if st.mode == Mode.AUTO and st.armed:
            return int(M.MISSION_STATE_ACTIVE)
        paused = st.mission_seq > 0 or self.last_reached >= 0
        return int(M.MISSION_STATE_PAUSED if paused else M.MISSION_STATE_NOT_STARTED)

    # --- events -------------------------------------------------------------------------
    def statustext(self, text: str, severity: int = M.MAV_SEVERITY_INFO) -> list[mavlink2.MAVLink_message]:
        """STATUSTEXT, split into MAVLink 2 chunks (id, chunk_seq) when longer than 50."""
        data = text.encode("utf-8", "replace")
        if len(data) <= STATUSTEXT_LEN:
            return [self.mav.statustext_encode(severity, data, 0, 0)]
        self._statustext_id = self._statustext_id % 0xFFFF + 1
        chunks = [data[i:i + STATUSTEXT_LEN] for i in range(0, len(data), STATUSTEXT_LEN)]
        if len(chunks[-1]) == STATUSTEXT_LEN:
            chunks.append(b"")  # the terminating short chunk tells the receiver the text is whole
        return [self.mav.statustext_encode(severity, c, self._statustext_id, n) for n, c in enumerate(chunks)]

    def event(self, ev: VehicleEvent) -> list[mavlink2.MAVLink_message]:
        if ev.kind == "mission_item_reached":
            self.last_reached = ev.seq
            out = [self.mav.mission_item_reached_encode(ev.seq)]
            return out + (self.statustext(ev.text, ev.severity) if ev.text else [])
        return self.statustext(ev.text or ev.kind, ev.severity)

    def mission_changed(self) -> None:
        self.last_reached = -1
