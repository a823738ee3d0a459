"""Coordinate conversions between the robot's world frame and MAVLink frames.

World (firmware_py.robot_spec): x east, y north, millimetres; heading CCW from east. MAVLink
LOCAL_NED: x north, y east, z down, metres; yaw clockwise from north. Global: latitude/longitude in
1e-7 degrees around the configured origin (the world's (0, 0)), with ArduPilot's flat-earth scaling,
accurate to millimetres over an arena.

Not in the control path: float maths is fine here.
"""

from __future__ import annotations

import math

# MAVLink's integer encoding of a local (LOCAL_NED) position in MISSION_ITEM_INT and
# COMMAND_INT x/y: metres * 1e4 (0.1 mm steps)
LOCAL_ITEM_SCALE = 10_000

# metres per 1e-7 degree of latitude (ArduPilot's LOCATION_SCALING_FACTOR)
M_PER_E7 = 0.011131884502145034


def world_to_ned_m(x_mm: int, y_mm: int) -> tuple[float, float]:
    """World (east, north mm) -> NED (north, east) metres."""
    return y_mm / 1000.0, x_mm / 1000.0


def ned_m_to_world(north_m: float, east_m: float) -> tuple[int, int]:
    """NED (north, east) metres -> world (x east, y north) mm."""
    return round(east_m * 1000.0), round(north_m * 1000.0)


def heading_to_yaw(heading_mrad: int) -> float:
    """World heading (CCW from east, mrad) -> NED yaw (CW from north, rad, -pi..pi)."""
    yaw = math.pi / 2 - heading_mrad / 1000.0
    return math.atan2(math.sin(yaw), math.cos(yaw))


def _lon_scale(lat_e7: int) -> float:
    return max(math.cos(math.radians(lat_e7 * 1e-7)), 0.01)


def world_to_global(x_mm: int, y_mm: int, origin_lat_e7: int, origin_lon_e7: int) -> tuple[int, int]:
    """World mm -> (lat_e7, lon_e7)."""
    north_m, east_m = world_to_ned_m(x_mm, y_mm)
    lat = origin_lat_e7 + round(north_m / M_PER_E7)
    lon = origin_lon_e7 + round(east_m / (M_PER_E7 * _lon_scale(origin_lat_e7)))
    return lat, lon


def global_to_world(lat_e7: int, lon_e7: int, origin_lat_e7: int, origin_lon_e7: int) -> tuple[int, int]:
    """(lat_e7, lon_e7) -> world mm."""
    north_m = (lat_e7 - origin_lat_e7) * M_PER_E7
    east_m = (lon_e7 - origin_lon_e7) * M_PER_E7 * _lon_scale(origin_lat_e7)
    return ned_m_to_world(north_m, east_m)


def local_item_to_global(x: int, y: int, origin_lat_e7: int, origin_lon_e7: int) -> tuple[int, int]:
    """A MISSION_ITEM_INT position in MAV_FRAME_LOCAL_NED (x north, y east, metres *
    LOCAL_ITEM_SCALE) -> (lat_e7, lon_e7) around the origin: what a ground station
    sends so that maps place the item, and what `global_to_world` brings back to the
    same world point within 1e-7 deg / 2 (<= 5.6 mm north, <= 5.6 mm * cos(lat0) east)."""
    x_mm, y_mm = ned_m_to_world(x / LOCAL_ITEM_SCALE, y / LOCAL_ITEM_SCALE)
    return world_to_global(x_mm, y_mm, origin_lat_e7, origin_lon_e7)


def offset_to_world(x_mm: int, y_mm: int, heading_mrad: int, frame_body: bool,
                    x_m: float, y_m: float) -> tuple[int, int]:
    """A position target relative to the robot -> world mm, as ArduPilot Rover reads them:
    LOCAL_OFFSET_NED (`frame_body` False: x north, y east metres from the robot) or BODY_NED /
    BODY_OFFSET_NED (True: x forward, y right metres from the robot, rotated by its heading)."""
    if not frame_body:
        dx, dy = ned_m_to_world(x_m, y_m)
        return x_mm + dx, y_mm + dy
    h = heading_mrad / 1000.0
    east = x_m * math.cos(h) + y_m * math.sin(h)  # forward along the heading, right is heading - 90 deg
    north = x_m * math.sin(h) - y_m * math.cos(h)
    return x_mm + round(east * 1000.0), y_mm + round(north * 1000.0)
