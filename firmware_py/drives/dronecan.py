"""The `dronecan` backends: DroneCAN ESCs for the wheels and DroneCAN rangefinders for the sectors.

The robot is one DroneCAN node (firmware_py/dronecan_engine.py). What it sends and hears for the
drive (`[drive] backend = "dronecan"`: esc.RPMCommand or, with `command = "raw"`, esc.RawCommand
from a wheel-speed PI; odometry and health from esc.Status and the ESC nodes' NodeStatus) and for
the sensors (`[sensors] backend = "dronecan"`: range_sensor.Measurement, `sensor_id` mapped by
`sensor_ids`): docs/robot-profile.md, "The `dronecan` backends".

Either way the node answers GetNodeInfo behind the tick's wheel command, one answer a tick at most
(dronecan_engine.py bounds reassembly and answers), and another node using the robot's node id
(a node-id collision) is reported by `check` as `arm_block`: the controller refuses to arm while
one is seen (the text becomes the refusal's STATUSTEXT), and `qnav-robot --check` lists it.

The bumper and the battery stay on qnav's frames. Needs the `dronecan` extra.
"""

from __future__ import annotations

import logging
import math
import threading
from typing import Any

import can
import dronecan

from firmware_py import can_protocol as proto
from firmware_py import robot_spec
from firmware_py.control.io import Outputs
from firmware_py.drives.base import DriveBackend, InputUpdate
from firmware_py.dronecan_engine import PRIORITY_HIGH, DroneCanEngine, type_name
from firmware_py.profile import RobotProfile

STOP_TICKS = 5  # zero commands sent after the wheels should stop
RAW_MAX = 8191
HEALTH_NAMES = {0: "OK", 1: "WARNING", 2: "ERROR", 3: "CRITICAL"}

log = logging.getLogger(__name__)


class _Esc:
    def __init__(self, side: str, index: int, sign: int) -> None:
        self.side, self.index, self.sign = side, index, sign
        self.rpm = 0.0
        self.t_us: int | None = None
        self.new = False
        self.counts = 0.0
        self.node: int | None = None
        self.health = 0
        self.integral = 0.0

    def name(self) -> str:
        node = f", DroneCAN node {self.node}" if self.node is not None else ""
        return f"{self.side} ESC {self.index}{node}"


class DroneCanBackend(DriveBackend):
    """The robot's DroneCAN node with the drive part, the sensor part, or both."""

    name = "dronecan"

    def __init__(self, profile: RobotProfile, *, drive: bool, sensors: bool, clock: Any = None) -> None:
        dc = profile.dronecan
        self.engine = DroneCanEngine(dc.node_id, dc.node_name, **({"clock": clock} if clock else {}))
        self.profile = profile
        self.drive_on, self.sensors_on = drive, sensors
        d = profile.drive
        self.escs = [_Esc("left", d.left_node, d.left_sign), _Esc("right", d.right_node, d.right_sign)]
        self.motor_rpm_per_mm_s = 60.0 * d.gear_ratio / profile.wheel_circumference_mm()
        self.max_rpm = d.max_rpm or math.ceil(d.max_speed_mm_s * self.motor_rpm_per_mm_s)
        self.enabled = False
        self._stop_left = 0
        n = len(profile.sensors.sensor_ids)  # one reading per sensor, any count (the profile's)
        self.max_ranges = profile.sensors.ranges_mm()
        self.sector_of = {sid: i for i, sid in enumerate(profile.sensors.sensor_ids)}
        self.ranges = [0] * n
        self.status = [robot_spec.RANGE_INVALID] * n
        self._fresh = [False] * n
        self.frames_sent = 0
        self._collision_said = ""
        self._lock = threading.Lock()

    # --- in ----------------------------------------------------------------------------
    def take(self, msg: can.Message, now_us: int) -> list[InputUpdate] | None:
        if not msg.is_extended_id:
            return None  # every DroneCAN frame is extended; standard ids are qnav's (or an ODrive's)
        with self._lock:
            tr = self.engine.take(msg, now_us / 1e6)
            if tr is None or tr.service_not_message:
                return []
            name = type_name(tr)
            if name == "uavcan.equipment.esc.Status" and self.drive_on:
                return self._esc_status(tr, now_us)
            if name == "uavcan.equipment.range_sensor.Measurement" and self.sensors_on:
                return self._range(tr.payload)
            if name == "uavcan.protocol.NodeStatus":
                for esc in self.escs:
                    if esc.node == tr.source_node_id:
                        esc.health = int(tr.payload.health)
            return []

    def _esc_status(self, tr: Any, now_us: int) -> list[InputUpdate]:
        p = tr.payload
        esc = next((e for e in self.escs if e.index == int(p.esc_index)), None)
        if esc is None:
            return []
        rpm = float(p.rpm)
        if esc.t_us is not None:  # the rpm an ESC reports is filtered: taken as the mean since its last Status
            dt = min(max(now_us - esc.t_us, 0), 200_000) / 1e6
            turns = esc.sign * rpm / 60.0 * dt / self.profile.drive.gear_ratio
            esc.counts += turns * self.profile.geometry.encoder_counts_per_rev
        esc.rpm, esc.t_us, esc.new, esc.node = rpm, now_us, True, tr.source_node_id
        if not all(e.new for e in self.escs):
            return []
        for e in self.escs:
            e.new = False
        left, right = (proto.wrap_counts(round(e.counts)) for e in self.escs)
        return [InputUpdate("enc", {"enc_left": left, "enc_right": right}),
                InputUpdate("driver", self._driver_fields())]

    def _driver_fields(self) -> dict[str, Any]:
        bad = [e for e in self.escs if e.health >= 2]
        detail = f"{bad[0].name()}: health {HEALTH_NAMES.get(bad[0].health, bad[0].health)}" if bad else ""
        return {"driver_state": proto.MOTOR_RUNNING if self.enabled else proto.MOTOR_IDLE,
                "driver_errors": sum(1 << i for i, e in enumerate(self.escs) if e.health >= 2),
                "driver_detail": detail, "driver_estop": False}

    def _range(self, p: Any) -> list[InputUpdate]:
        i = self.sector_of.get(int(p.sensor_id))
        if i is None:
            return []
        kind = int(p.reading_type)
        rng = float(p.range)
        if kind == robot_spec.RANGE_TOO_FAR:
            mm = self.max_ranges[i]
        elif kind == robot_spec.RANGE_TOO_CLOSE:
            mm = robot_spec.RANGE_MIN_MM
        elif kind == robot_spec.RANGE_VALID and math.isfinite(rng) and rng >= 0:
            mm = min(4095, round(rng * 1000))
        else:
            kind, mm = robot_spec.RANGE_INVALID, 0
        self.ranges[i], self.status[i] = mm, kind  # checked against the sensor's range by the controller
        self._fresh[i] = True
        n = len(self.ranges)
        per = (n + 1) // 2  # two halves, as qnav's two RangeSectors frames (4 + 4 of 8)
        out = []
        for f in range(len(proto.RANGE_SECTORS_IDS)):
            half = range(f * per, min(n, (f + 1) * per))
            if i in half and all(self._fresh[k] for k in half):
                for k in half:
                    self._fresh[k] = False
                out.append(InputUpdate(f"ranges{f}", {"ranges_mm": list(self.ranges),
                                                      "range_status": list(self.status)}))
        return out

    def collision(self, now_us: int) -> str:
        """Another node using our node id (the engine's words), '' when none is seen."""
        with self._lock:
            text = self.engine.collision(now_us / 1e6)
        if text and not self._collision_said:
            log.warning("%s", text)
        self._collision_said = text
        return text

    def check(self, now_us: int, timeout_us: int) -> list[InputUpdate]:
        block = InputUpdate("", {"arm_block": self.collision(now_us)})
        if not self.drive_on:
            return [block]
        with self._lock:
            fields = self._driver_fields()
            if not fields["driver_detail"]:
                for e in self.escs:
                    if e.t_us is None or now_us - e.t_us > timeout_us:
                        since = "none heard" if e.t_us is None else f"none for {(now_us - e.t_us) // 1000} ms"
                        fields["driver_detail"] = f"{e.name()}: esc.Status {since}"
                        break
            return [InputUpdate("", {"driver_errors": fields["driver_errors"],
                                     "driver_detail": fields["driver_detail"]}), block]

    # --- out ---------------------------------------------------------------------------
    def frames(self, out: Outputs, now_us: int) -> list[can.Message]:
        with self._lock:
            msgs: list[can.Message] = []  # the wheel command first, then NodeStatus, then answers (rate-limited)
            if self.drive_on:
                want = out.drive_enabled and out.motor is not None
                if want:
                    assert out.motor is not None
                    self.enabled, self._stop_left = True, STOP_TICKS
                    msgs += self._command((out.motor.left_mm_s, out.motor.right_mm_s))
                elif self._stop_left > 0:
                    self.enabled = False
                    self._stop_left -= 1
                    msgs += self._command((0, 0))  # a zero target also resets each ESC's PI integral
            msgs += self.engine.periodic(now_us / 1e6)
            msgs += self.engine.outgoing(now_us / 1e6)
            self.frames_sent += len(msgs)
            return msgs

    def _command(self, wheel_mm_s: tuple[int, int]) -> list[can.Message]:
        n = max(e.index for e in self.escs) + 1
        target = [e.sign * wheel_mm_s[k] * self.motor_rpm_per_mm_s for k, e in enumerate(self.escs)]
        if self.profile.drive.command == "rpm":
            rpm = [0] * n
            for e, t in zip(self.escs, target, strict=True):
                rpm[e.index] = max(-131072, min(131071, round(t)))
            return self.engine.broadcast(dronecan.uavcan.equipment.esc.RPMCommand(rpm=rpm), PRIORITY_HIGH)
        raw = [0] * n
        period_s = robot_spec.CONTROL_PERIOD_US / 1e6
        for e, t in zip(self.escs, target, strict=True):
            if t == 0:
                e.integral = 0.0
                continue
            err = t - e.rpm  # a wheel-speed PI on the ESC's own rpm, feed-forward on top
            e.integral = max(-0.3 * self.max_rpm, min(0.3 * self.max_rpm, e.integral + err * period_s * 2.0))
            cmd = (t + 0.3 * err + e.integral) / self.max_rpm * RAW_MAX
            raw[e.index] = max(-RAW_MAX, min(RAW_MAX, round(cmd)))
        return self.engine.broadcast(dronecan.uavcan.equipment.esc.RawCommand(cmd=raw), PRIORITY_HIGH)

    def stats(self) -> dict[str, Any]:
        e = self.engine
        return {"dronecan_node_id": e.node_id, "dronecan_bad_transfers": e.bad_transfers,
                "dronecan_dropped_transfers": e.rx.dropped, "dronecan_timed_out_transfers": e.rx.timed_out,
                "dronecan_ignored_frames": e.rx.ignored, "dronecan_node_info_answers": e.answered_info,
                "dronecan_node_info_dropped": e.answers.dropped, "dronecan_collision_frames": e.collision_frames,
                "drive_frames_sent": self.frames_sent}
