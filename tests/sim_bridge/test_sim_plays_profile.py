"""The sim plays the robot profile it is given (issue 44 item 2), not the built-in robot.

With tests/sim_bridge/profiles/wide_geared_odrive.toml (320 mm wheel base, 50 mm wheels, 180 mm
body, 4096 counts per turn, ODrive axes on nodes 3/4 geared 7.5:1 with the left one mirrored, eight
range sensors at uneven angles out of angle order, 1200 mm range) the plant is driven tick by tick,
as in lockstep (its frames out, the wheel command in, one control period of physics), with a fixed
wheel command, and the truth (the pymunk body) is compared with what the profile's robot would make
of the frames:

* (a) the ODrive encoder estimates (motor turns) and qnav's EncoderCounts integrate, with the
  profile's wheel, gear ratio and signs, to the true travel within 1 %;
* (b) opposite wheel speeds turn the body at the rate the profile's wheel base gives, within 2 %;
* (c) the body stops at a wall at the profile's radius;
* (d) a post at one sensor's angle is seen by that sensor's reading and no other (the profile's
  angles, in its order, its range), on qnav's RangeSectors frames (8 sectors, the frames' count) and
  on DroneCAN Measurements with six sensors (a count the profile loader refuses in this build, so
  that variant is built from the fixture with `dataclasses.replace`).
"""

from __future__ import annotations

import math
import struct
from dataclasses import replace
from pathlib import Path

import can
import numpy as np
import pytest

from firmware_py import can_protocol as cp
from firmware_py import robot_spec
from firmware_py.profile import DEFAULT, DriveConfig, RobotProfile, SensorConfig, load_profile
from sim_bridge.obstacles import ObstacleLayer
from sim_bridge.plant import Plant, SimConfig
from sim_bridge.sensors import RangeParams
from sim_bridge.world import Pose

WIDE = Path(__file__).resolve().parent / "profiles" / "wide_geared_odrive.toml"
CELL_M = 0.5


@pytest.fixture(scope="module")
def wide() -> RobotProfile:
    return load_profile(WIDE)


def qnav_drive(p: RobotProfile) -> RobotProfile:
    """The same robot with qnav's motor driver (MotorCommand, EncoderCounts) instead of the ODrives."""
    return replace(p, drive=DriveConfig())


class Driver:
    """The robot's side of the bus, reduced to a fixed wheel command and its odometry: each tick
    takes the plant's frames, answers with the wheel command in the profile's drive backend, and
    the physics runs one control period."""

    def __init__(self, plant: Plant, profile: RobotProfile) -> None:
        self.plant, self.p = plant, profile
        self.circ_mm = 2 * math.pi * profile.geometry.wheel_radius_mm
        d = profile.drive
        self.nodes = (d.left_node, d.right_node)
        self.signs = (d.left_sign, d.right_sign)
        self.pos: dict[int, float] = {}  # ODrive node -> last Pos_Estimate (motor turns)
        self.counts: tuple[int, int] | None = None  # last EncoderCounts
        self.ranges: dict[int, tuple[int, int]] = {}
        self.frames: list = []
        if d.backend == "odrive":
            for node in self.nodes:  # velocity control, passthrough; closed loop
                self._send(node << 5 | 0x0B, struct.pack("<II", 2, 1))
                self._send(node << 5 | 0x07, struct.pack("<I", 8))

    def _send(self, arb: int, data: bytes) -> None:
        self.plant.handle(can.Message(arbitration_id=arb, data=data, is_extended_id=False))

    def tick(self, left_mm_s: float, right_mm_s: float) -> None:
        plant = self.plant
        self.frames = plant.tick_frames()
        for f in self.frames:
            node, cmd = f.arbitration_id >> 5, f.arbitration_id & 0x1F
            if not f.is_extended_id and node in self.nodes and cmd == 0x09 and self.p.drive.backend == "odrive":
                self.pos[node] = struct.unpack("<ff", bytes(f.data))[0]
            elif f.arbitration_id == cp.DB.get_message_by_name("EncoderCounts").frame_id:
                sig = cp.decode(f)[1]
                self.counts = (sig["Enc_Left"], sig["Enc_Right"])
            elif f.arbitration_id in cp.RANGE_SECTORS_IDS:
                self.ranges.update(cp.ranges_from(*cp.decode(f)))
        if self.p.drive.backend == "odrive":
            g = self.p.drive.gear_ratio
            for node, sign, v in zip(self.nodes, self.signs, (left_mm_s, right_mm_s), strict=True):
                self._send(node << 5 | 0x0D, struct.pack("<ff", sign * v / self.circ_mm * g, 0.0))
        else:
            plant.handle(cp.motor_command(round(left_mm_s), round(right_mm_s), plant.tick))
        plant.step_period()

    def wheel_travel_mm(self) -> tuple[float, float]:
        """Each wheel's travel as the profile's robot computes it from the frames."""
        if self.p.drive.backend == "odrive":
            g = self.p.drive.gear_ratio
            return tuple(sign * self.pos[node] / g * self.circ_mm  # type: ignore[return-value]
                         for node, sign in zip(self.nodes, self.signs, strict=True))
        assert self.counts is not None
        per = self.p.geometry.encoder_counts_per_rev
        return (self.counts[0] / per * self.circ_mm, self.counts[1] / per * self.circ_mm)

    def run(self, seconds: float, left_mm_s: float, right_mm_s: float) -> None:
        for _ in range(round(seconds * 1e6 / robot_spec.CONTROL_PERIOD_US)):
            self.tick(left_mm_s, right_mm_s)


def make_plant(profile: RobotProfile | None, rows: int, cols: int, start: Pose) -> Plant:
    occ = np.zeros((rows, cols), bool)
    config = SimConfig(cell_size_m=CELL_M, ranges=RangeParams(noise_std_mm=0.0), robot=profile)
    return Plant(occ, config, start)


@pytest.mark.parametrize("backend", ["odrive", "qnav"])
def test_a_the_encoders_integrate_with_the_profiles_wheel_and_gear_to_the_true_travel(wide, backend):
    prof = wide if backend == "odrive" else qnav_drive(wide)
    plant = make_plant(prof, 6, 12, Pose(1.0, 1.5, 0.0))  # 6 x 3 m, open
    drv = Driver(plant, prof)
    drv.run(7.0, 300, 300)
    drv.tick(300, 300)  # the frames of the pose reached (the physics after them is not counted)
    true_mm = (plant.trajectory[-2][2] - 1.0) * 1000
    assert true_mm > 1900
    for wheel in drv.wheel_travel_mm():
        assert wheel == pytest.approx(true_mm, rel=0.01), (backend, drv.wheel_travel_mm(), true_mm)


@pytest.mark.parametrize("backend", ["odrive", "qnav"])
def test_b_opposite_wheel_speeds_turn_at_the_profiles_wheel_base(wide, backend):
    prof = wide if backend == "odrive" else qnav_drive(wide)
    plant = make_plant(prof, 8, 8, Pose(2.0, 2.0, 0.0))
    drv = Driver(plant, prof)
    drv.run(1.0, -200, 200)  # past the motors' ramp
    h0, t0 = plant.world.body.angle, plant.time_us
    drv.run(3.0, -200, 200)
    rate = (plant.world.body.angle - h0) / ((plant.time_us - t0) / 1e6)
    want = 2 * 200 / wide.geometry.wheel_base_mm  # rad/s: (v_r - v_l) / base
    assert rate == pytest.approx(want, rel=0.02), (rate, want)


@pytest.mark.parametrize("which", ["built-in", "wide"])
def test_c_the_body_meets_a_wall_at_the_profiles_radius(wide, which):
    prof = None if which == "built-in" else qnav_drive(wide)
    radius_mm = (DEFAULT if prof is None else prof).geometry.robot_radius_mm
    plant = make_plant(prof, 6, 12, Pose(5.0, 1.5, 0.0))  # the east wall at x = 6 m
    drv = Driver(plant, prof or DEFAULT)
    drv.run(6.0, 200, 200)
    gap_mm = (6.0 - plant.world.pose.x) * 1000
    assert gap_mm == pytest.approx(radius_mm, abs=2.0), (which, gap_mm)
    assert plant.world.contacts  # pressing on it


def _post_at(plant: Plant, angle_deg: float, dist_m: float, r_m: float) -> None:
    pose = plant.world.pose
    a = pose.heading + math.radians(angle_deg)
    ObstacleLayer(plant.world, [[(pose.x + dist_m * math.cos(a)) * 1000, (pose.y + dist_m * math.sin(a)) * 1000,
                                 r_m * 1000]], [])


@pytest.mark.parametrize("k", range(8))
def test_d_a_post_at_one_sensors_angle_is_that_readings_on_qnav_frames(wide, k):
    angles = wide.sensors.angles_deg
    plant = make_plant(wide, 12, 12, Pose(3.0, 3.0, math.radians(30)))  # walls 3 m away, beyond reach
    _post_at(plant, angles[k], 0.7, 0.05)
    drv = Driver(plant, qnav_drive(wide))
    drv.tick(0, 0)
    want = 700 - 50 - wide.geometry.robot_radius_mm  # from the rim of the profile's body
    seen = {i: r for i, r in drv.ranges.items() if r[1] != robot_spec.RANGE_TOO_FAR}
    assert list(seen) == [k], (k, drv.ranges)
    assert seen[k][0] == pytest.approx(want, abs=3) and seen[k][1] == robot_spec.RANGE_VALID
    # nothing in reach: the profile's maximum range
    assert all(drv.ranges[i] == (wide.sensors.max_range_mm, robot_spec.RANGE_TOO_FAR) for i in range(8) if i != k)


SIX = SensorConfig(backend="dronecan", angles_deg=(15.0, 120.0, 70.0, -160.0, -100.0, -45.0), max_range_mm=1200,
                   sensor_ids=(21, 5, 9, 40, 33, 2))


def _measurements(frames) -> dict[int, tuple[float, int]]:
    """sensor_id -> (range m, reading_type) from the frames' DroneCAN range_sensor.Measurements."""
    dronecan = pytest.importorskip("dronecan")
    from dronecan.driver.common import CANFrame

    from sim_bridge.dronecan_boards import QueueDriver

    driver = QueueDriver()
    node = dronecan.node.Node(driver, node_id=99)
    got: dict[int, tuple[float, int]] = {}
    node.add_handler(dronecan.uavcan.equipment.range_sensor.Measurement,
                     lambda e: got.__setitem__(e.message.sensor_id, (e.message.range, e.message.reading_type)))
    for f in frames:
        if f.is_extended_id:
            driver.rx.append(CANFrame(f.arbitration_id, bytearray(f.data), True))
            node.spin(0)
    node.close()
    return got


@pytest.mark.parametrize("k", range(6))
def test_d_six_dronecan_rangefinders_at_the_profiles_angles_in_its_order(wide, k):
    pytest.importorskip("dronecan")
    prof = replace(wide, sensors=SIX)  # six sensors: load_profile wants 8 in this build (robot side)
    plant = make_plant(prof, 12, 12, Pose(3.0, 3.0, math.radians(-50)))
    _post_at(plant, SIX.angles_deg[k], 0.7, 0.05)
    drv = Driver(plant, prof)
    drv.tick(0, 0)
    assert not drv.ranges  # no qnav RangeSectors frames: the sensors are DroneCAN's
    got = _measurements(drv.frames)
    assert sorted(got) == sorted(SIX.sensor_ids)
    seen = {sid: r for sid, r in got.items() if r[1] != robot_spec.RANGE_TOO_FAR}
    assert list(seen) == [SIX.sensor_ids[k]], (k, got)
    want_m = (700 - 50 - wide.geometry.robot_radius_mm) / 1000
    assert seen[SIX.sensor_ids[k]][0] == pytest.approx(want_m, abs=0.004)
    assert all(r == (pytest.approx(1.2, abs=0.002), robot_spec.RANGE_TOO_FAR) for sid, r in got.items()
               if sid != SIX.sensor_ids[k])


def test_eight_sensors_on_qnav_frames_is_said_for_another_count(wide):
    prof = replace(wide, sensors=replace(SIX, backend="qnav"))
    with pytest.raises(ValueError, match="6 range sensors: qnav's RangeSectors frames carry 8"):
        make_plant(prof, 12, 12, Pose(3.0, 3.0, 0.0))


def test_the_built_in_robot_is_the_default_profile():
    a = make_plant(None, 6, 6, Pose(1.5, 1.5, 0.0))
    b = make_plant(DEFAULT, 6, 6, Pose(1.5, 1.5, 0.0))
    for p in (a, b):
        assert p.world.radius_m * 1000 == robot_spec.ROBOT_RADIUS_MM
        assert p.world.half_base_m * 2000 == robot_spec.WHEEL_BASE_MM
        assert p.ranges.angles_mrad == list(robot_spec.SENSOR_ANGLES_MRAD)
        assert p.ranges.max_range_mm == robot_spec.RANGE_MAX_MM
        assert p.encoders.counts_per_rev == robot_spec.ENCODER_TICKS_PER_REV
    assert a.ranges.read() == b.ranges.read()
