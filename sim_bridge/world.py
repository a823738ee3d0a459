"""The pymunk arena and the robot body.

Owns the physical world: static boxes for obstacle cells (each row's runs of obstacle cells merged
into one box), four outer walls, and the robot as a circle driven the way pymunk's tank example
drives its tank — a kinematic control body carries the wanted velocity and a `PivotJoint`
(max_bias=0, finite max_force) plus a `GearJoint` pull the robot after it. The solver then stops the
robot at walls at any commanded speed; setting the body's velocity directly would tunnel through
them.

The body's radius and wheel base are the robot profile's (`firmware_py.profile.Geometry`; the
default is the built-in robot of `robot_spec`).

Units are SI (metres, seconds, radians); the world frame is robot_spec.py's: x east along columns, y
north, map row 0 is the northernmost row.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pymunk

from firmware_py import robot_spec
from firmware_py.profile import DEFAULT as DEFAULT_ROBOT
from firmware_py.profile import Geometry

ROBOT_TYPE = 1  # collision types
WALL_TYPE = 2
ROBOT_CATEGORY = 0b1  # shape filter category of the robot: rays exclude it
WORLD_CATEGORY = 0b10


def as_wall(shape: pymunk.Shape) -> pymunk.Shape:
    """`shape` made a wall of the arena: frictionless, inelastic, hit by the range rays (not the
    robot's category), a bumper contact on touch (the walls' collision type)."""
    shape.friction = 0.0
    shape.elasticity = 0.0
    shape.collision_type = WALL_TYPE
    shape.filter = pymunk.ShapeFilter(categories=WORLD_CATEGORY)
    return shape


@dataclass(frozen=True)
class Pose:
    x: float
    y: float
    heading: float


@dataclass(frozen=True)
class BodyParams:
    mass_kg: float = 3.0
    traction_accel_m_s2: float = 10.0  # max linear accel the wheels can transmit (friction ~1 g)
    traction_ang_accel_rad_s2: float = 80.0


class World:
    """pymunk space with the map's obstacles and one differential-drive robot."""

    def __init__(self, occ: np.ndarray, cell_size_m: float = robot_spec.DEFAULT_CELL_SIZE_MM / 1000,
                 start: Pose | None = None, body: BodyParams = BodyParams(),
                 geometry: Geometry = DEFAULT_ROBOT.geometry) -> None:
        occ = np.asarray(occ, dtype=bool)
        if occ.ndim != 2 or occ.size == 0:
            raise ValueError(f"occupancy grid must be a non-empty 2-D array, got shape {occ.shape}")
        if not cell_size_m > 0:
            raise ValueError(f"cell size must be positive, got {cell_size_m}")
        self.occ = occ
        self.cell_size_m = float(cell_size_m)
        self.height, self.width = occ.shape
        self.size_m = (self.width * self.cell_size_m, self.height * self.cell_size_m)
        self.geometry = geometry  # the profile's: body radius (the pymunk circle), wheel base (kinematics)
        self.radius_m = geometry.robot_radius_mm / 1000
        self.half_base_m = geometry.wheel_base_mm / 2000

        space = pymunk.Space()
        space.gravity = (0.0, 0.0)
        space.collision_slop = 0.0005  # metres: the default 0.1 would allow 10 cm overlap
        space.iterations = 10
        self.space = space
        self._add_obstacles()

        mass = body.mass_kg
        moment = pymunk.moment_for_circle(mass, 0, self.radius_m)
        self.body = pymunk.Body(mass, moment)
        pose = start if start is not None else self.default_start()
        self.check_start(pose)
        self.body.position = (pose.x, pose.y)
        self.body.angle = pose.heading
        self.shape = pymunk.Circle(self.body, self.radius_m)
        self.shape.friction = 0.0  # sliding along walls, no wall-induced spin
        self.shape.elasticity = 0.0
        self.shape.collision_type = ROBOT_TYPE
        self.shape.filter = pymunk.ShapeFilter(categories=ROBOT_CATEGORY)
        self.control = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        self.control.position = self.body.position
        self.control.angle = self.body.angle
        pivot = pymunk.PivotJoint(self.control, self.body, (0, 0), (0, 0))
        pivot.max_bias = 0  # velocity only: no positional correction
        pivot.max_force = mass * body.traction_accel_m_s2
        gear = pymunk.GearJoint(self.control, self.body, 0.0, 1.0)
        gear.max_bias = 0
        gear.max_force = moment * body.traction_ang_accel_rad_s2
        space.add(self.body, self.shape, self.control, pivot, gear)

        # Bumper state, kept by collision handlers (see sensors.Bumper for the frame).
        self.contacts: dict[int, float] = {}  # wall shape id -> contact angle (world rad)
        self.contact_events = 0
        self.last_contact_angle = 0.0
        space.on_collision(ROBOT_TYPE, WALL_TYPE, begin=self._begin, pre_solve=self._touching,
                           separate=self._separate)

    # --- construction ------------------------------------------------------
    def _add_box(self, x0: float, y0: float, x1: float, y1: float) -> None:
        corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
        self.space.add(as_wall(pymunk.Poly(self.space.static_body, corners)))

    def _add_obstacles(self) -> None:
        c, h = self.cell_size_m, self.height
        for row in range(h):
            cols = np.flatnonzero(self.occ[row])
            if cols.size == 0:
                continue
            # split the row's obstacle columns into runs of consecutive cells
            breaks = np.flatnonzero(np.diff(cols) > 1)
            starts = np.concatenate(([cols[0]], cols[breaks + 1]))
            ends = np.concatenate((cols[breaks], [cols[-1]]))
            y0, y1 = (h - row - 1) * c, (h - row) * c
            for a, b in zip(starts, ends, strict=True):
                self._add_box(a * c, y0, (b + 1) * c, y1)
        w_m, h_m = self.size_m
        t = 1.0  # outer wall thickness, metres
        self._add_box(-t, -t, w_m + t, 0.0)
        self._add_box(-t, h_m, w_m + t, h_m + t)
        self._add_box(-t, 0.0, 0.0, h_m)
        self._add_box(w_m, 0.0, w_m + t, h_m)

    def default_start(self) -> Pose:
        """Centre of the free cell nearest the map centre, heading east."""
        free = np.argwhere(~self.occ)
        if free.size == 0:
            raise ValueError("map has no free cell to start in")
        centre = np.array([(self.height - 1) / 2, (self.width - 1) / 2])
        row, col = free[np.argmin(((free - centre) ** 2).sum(axis=1))]
        return Pose(*self.cell_center(int(col), int(row)), 0.0)

    def cell_center(self, col: int, row: int) -> tuple[float, float]:
        return ((col + 0.5) * self.cell_size_m, (self.height - row - 0.5) * self.cell_size_m)

    def check_start(self, pose: Pose) -> None:
        """Raise ValueError unless the robot disc fits at `pose` inside the arena."""
        w_m, h_m = self.size_m
        r = self.radius_m
        if not (r <= pose.x <= w_m - r and r <= pose.y <= h_m - r):
            raise ValueError(f"start ({pose.x:.3f}, {pose.y:.3f}) m puts the robot outside the "
                             f"{w_m:.2f} x {h_m:.2f} m arena")
        walls_only = pymunk.ShapeFilter(mask=pymunk.ShapeFilter.ALL_MASKS() ^ ROBOT_CATEGORY)
        if self.space.point_query((pose.x, pose.y), r * 0.999, walls_only):
            raise ValueError(f"start ({pose.x:.3f}, {pose.y:.3f}) m overlaps an obstacle")

    # --- collision handlers -------------------------------------------------
    def _contact_angle(self, arbiter: pymunk.Arbiter) -> float | None:
        points = arbiter.contact_point_set.points
        if not points:
            return None
        px, py = points[0].point_a
        bx, by = self.body.position
        return math.atan2(py - by, px - bx)

    def _begin(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: object) -> None:
        self.contact_events += 1
        self._touching(arbiter, space, data)

    def _touching(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: object) -> None:
        angle = self._contact_angle(arbiter)
        if angle is not None:
            self.contacts[id(arbiter.shapes[1])] = angle
            self.last_contact_angle = angle

    def _separate(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: object) -> None:
        self.contacts.pop(id(arbiter.shapes[1]), None)

    # --- driving ------------------------------------------------------------
    def drive(self, left_m_s: float, right_m_s: float) -> None:
        """Set the wheel surface speeds the motors want for the next step."""
        v = (left_m_s + right_m_s) / 2
        omega = (right_m_s - left_m_s) / (2 * self.half_base_m)
        heading = self.body.angle
        self.control.position = self.body.position
        self.control.angle = heading
        self.control.velocity = (v * math.cos(heading), v * math.sin(heading))
        self.control.angular_velocity = omega

    def step(self, dt_s: float) -> None:
        self.space.step(dt_s)

    @property
    def pose(self) -> Pose:
        x, y = self.body.position
        return Pose(x, y, self.body.angle)

    def wheel_ground_speeds(self) -> tuple[float, float]:
        """(left, right) m/s of the wheel contact points along the heading."""
        heading = self.body.angle
        vx, vy = self.body.velocity
        v = vx * math.cos(heading) + vy * math.sin(heading)
        w = self.body.angular_velocity * self.half_base_m
        return v - w, v + w
