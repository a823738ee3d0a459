"""DroneCAN boards the sim plays: one ESC node per wheel and one rangefinder node, each a node of
the DroneCAN project's own library (`dronecan.node.Node`: NodeStatus, GetNodeInfo, transfer ids and
framing are the library's), on an in-memory driver whose frames the plant moves over the bus.

* ESCs (node 10 + ESC index): take `uavcan.equipment.esc.RPMCommand` (motor rpm) or `RawCommand`
  (-8191..8191 of `max_rpm`) at their index, drive their wheel through the plant's wheel model,
  stop after ESC_TIMEOUT_US without a command, and send `uavcan.equipment.esc.Status` (motor rpm,
  esc_index, voltage) every control period. A motor mounted the other way round (`flip`) turns its
  wheel backwards while its rpm still reads as commanded (the ESC measures the motor).
* the rangefinder node (node 20) sends one `uavcan.equipment.range_sensor.Measurement` per sensor
  per control period: `sensor_id` from the profile, `reading_type` the sim's status (qnav's codes
  are DroneCAN's), range in metres.
* faults: an ESC's node reports health ERROR (`error:CODE` in --drive-fault) or falls silent.

Each node's NodeStatus goes out at 1 Hz of sim time (besides the library's own 1 Hz of wall time),
so a health change reaches the robot within a sim second however fast lockstep runs.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import can
import dronecan
from dronecan.driver.common import AbstractDriver, CANFrame

from firmware_py import robot_spec
from firmware_py.profile import RobotProfile
from sim_bridge.motors import MotorDriver

ESC_NODE_BASE = 10
RANGEFINDER_NODE = 20
ESC_TIMEOUT_US = 500_000
RAW_MAX = 8191


class QueueDriver(AbstractDriver):
    """A dronecan driver on two in-memory queues: frames in from the plant, frames out to it."""

    def __init__(self) -> None:
        super().__init__()
        self.rx: deque[CANFrame] = deque()
        self.tx: list[can.Message] = []

    def receive(self, timeout: float | None = None) -> CANFrame | None:
        return self.rx.popleft() if self.rx else None

    def send_frame(self, frame: CANFrame) -> None:
        self.tx.append(can.Message(arbitration_id=frame.id, data=bytes(frame.data), is_extended_id=True))

    def close(self) -> None:
        pass


def _node(node_id: int, name: str) -> tuple[Any, QueueDriver]:
    driver = QueueDriver()
    info = dronecan.uavcan.protocol.GetNodeInfo.Response()
    info.name = name
    node = dronecan.node.Node(driver, node_id=node_id, node_info=info,
                              mode=dronecan.uavcan.protocol.NodeStatus().MODE_OPERATIONAL)
    return node, driver


class _Esc:
    def __init__(self, index: int, mount_sign: int) -> None:
        self.index, self.mount_sign = index, mount_sign
        self.node, self.driver = _node(ESC_NODE_BASE + index, f"org.qnav.sim.esc{index}")
        self.rpm_cmd = 0.0
        self.last_us: int | None = None
        self.silent = False
        self.speed_sum, self.speed_n = 0.0, 0  # the wheel's speed over the period, for the rpm it reports


class DroneCanBoards:
    def __init__(self, profile: RobotProfile, motors: MotorDriver, *, drive: bool, sensors: bool,
                 flip: str = "") -> None:
        d = profile.drive
        self.profile, self.motors = profile, motors
        self.drive, self.sensors = drive, sensors
        self.gear = d.gear_ratio
        self.mm_per_turn = profile.wheel_circumference_mm()
        self.max_rpm = d.max_rpm or math.ceil(d.max_speed_mm_s * 60 * self.gear / self.mm_per_turn)
        self.escs = [_Esc(d.left_node, d.left_sign * (-1 if flip == "left" else 1)),
                     _Esc(d.right_node, d.right_sign * (-1 if flip == "right" else 1))] if drive else []
        self.ranger: Any = None
        self.ranger_driver: QueueDriver | None = None
        if sensors:
            self.ranger, self.ranger_driver = _node(RANGEFINDER_NODE, "org.qnav.sim.rangefinders")
        self.faults: list[tuple[int, str, str]] = []
        self.now_us = 0
        for esc in self.escs:
            esc.node.add_handler(dronecan.uavcan.equipment.esc.RPMCommand, self._on_rpm)
            esc.node.add_handler(dronecan.uavcan.equipment.esc.RawCommand, self._on_raw)
        self._next_status_us = 0

    def _nodes(self) -> list[tuple[Any, QueueDriver]]:
        out = [(e.node, e.driver) for e in self.escs]
        if self.ranger is not None and self.ranger_driver is not None:
            out.append((self.ranger, self.ranger_driver))
        return out

    # --- frames in -----------------------------------------------------------------------
    @staticmethod
    def owns(msg: can.Message) -> bool:
        return msg.is_extended_id and not msg.is_error_frame and not msg.is_remote_frame

    def handle(self, msg: can.Message, now_us: int) -> None:
        self.now_us = now_us
        frame = CANFrame(msg.arbitration_id, bytearray(msg.data), True)
        for node, driver in self._nodes():
            driver.rx.append(frame)
            node.spin(0)  # the library reassembles and calls the handlers (and answers GetNodeInfo)

    def _on_rpm(self, event: Any) -> None:
        self._command(event, [float(v) for v in event.message.rpm])

    def _on_raw(self, event: Any) -> None:
        self._command(event, [float(v) / RAW_MAX * self.max_rpm for v in event.message.cmd])

    def _command(self, event: Any, rpms: list[float]) -> None:
        esc = next((e for e in self.escs if e.node is event.node), None)  # the node that heard it
        if esc is None or esc.index >= len(rpms):
            return
        esc.rpm_cmd, esc.last_us = rpms[esc.index], self.now_us
        self._command_wheels()

    def _command_wheels(self) -> None:
        speeds = [e.mount_sign * e.rpm_cmd / 60 / self.gear * self.mm_per_turn for e in self.escs]
        if speeds:
            self.motors.command(round(speeds[0]), round(speeds[1]), 0, self.now_us)

    # --- time ----------------------------------------------------------------------------
    def step(self, now_us: int) -> None:
        """After a physics step: faults due, the ESCs' command timeout."""
        self.now_us = now_us
        for t, what, side in list(self.faults):
            if now_us >= t and self.escs:
                self.faults.remove((t, what, side))
                esc = self.escs[0 if side == "left" else 1]
                if what == "silent":
                    esc.silent = True
                else:
                    esc.node.health = dronecan.uavcan.protocol.NodeStatus().HEALTH_ERROR
                    esc.rpm_cmd = 0.0
        for e in self.escs:
            if e.last_us is not None and now_us - e.last_us >= ESC_TIMEOUT_US:
                e.rpm_cmd, e.last_us = 0.0, None
        self._command_wheels()
        for e, speed in zip(self.escs, self.motors.speed, strict=False):
            e.speed_sum += speed
            e.speed_n += 1

    def tick_frames(self, readings: list[tuple[int, int]]) -> list[can.Message]:
        """This period's Status and Measurement frames (and whatever the nodes had queued)."""
        for e, now in zip(self.escs, self.motors.speed, strict=False):
            # an ESC reports a filtered rpm: here the mean over the period since its last Status
            speed = e.speed_sum / e.speed_n if e.speed_n else now
            e.speed_sum, e.speed_n = 0.0, 0
            if e.silent:
                continue
            st = dronecan.uavcan.equipment.esc.Status()
            st.esc_index = e.index
            st.rpm = round(e.mount_sign * speed / self.mm_per_turn * 60 * self.gear)
            st.voltage = 12.0
            e.node.broadcast(st)
        if self.ranger is not None:
            half_fov = robot_spec.SENSOR_FOV_MRAD / 1000
            for i, (mm, status) in enumerate(readings):
                m = dronecan.uavcan.equipment.range_sensor.Measurement()
                m.sensor_id = self.profile.sensors.sensor_ids[i]
                m.sensor_type = m.SENSOR_TYPE_LIDAR
                m.field_of_view = half_fov
                m.reading_type = status
                m.range = mm / 1000.0
                self.ranger.broadcast(m)
        if self.now_us >= self._next_status_us:  # NodeStatus on sim time too: lockstep runs faster than 1 Hz
            self._next_status_us = self.now_us + 1_000_000
            for node, _driver in self._nodes():
                st = dronecan.uavcan.protocol.NodeStatus()
                st.uptime_sec, st.health, st.mode = self.now_us // 1_000_000, node.health, node.mode
                node.broadcast(st)
        out = []
        silent = [e.node for e in self.escs if e.silent]
        for node, driver in self._nodes():
            if node not in silent:
                node.spin(0)  # NodeStatus when due
                out += driver.tx
            driver.tx = []
        return out
