"""The re-planning core of `qnav mission upload --plan --follow` (ground_station/nav/replan.py),
fed with the robot's own telemetry encoding (firmware_py.mavlink.telemetry, packed and parsed by
pymavlink): map walls are never taken for obstacles, an unmapped reading is placed where it
was seen, a stall re-plans round it, and the last target reached ends the follow."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_py import robot_spec
from firmware_py.layout import Layout
from firmware_py.mavlink.dialect import mavlink2 as m
from firmware_py.mavlink.frames import LOCAL_ITEM_SCALE
from firmware_py.mavlink.params import ParamStore
from firmware_py.mavlink.telemetry import NodeStats, Telemetry
from firmware_py.profile import load_profile
from firmware_py.vehicle import VehicleStatus
from ground_station.learn.sector.twin import DEFAULT_TW, sense_one
from ground_station.maps import GridMap, MapError, load_map
from ground_station.nav.replan import (
    Finished,
    MissionFollower,
    Replan,
    UnmappedPoints,
    raster_plan,
    sensor_readings,
)
from tests.ground_station.test_nav_plan_cli import _run

GM = load_map("paper10")
OCC = np.ascontiguousarray(GM.occ, dtype=np.uint8)
MAV = m.MAVLink(None, srcSystem=1, srcComponent=1)
TEL = Telemetry(MAV, ParamStore())


def _map_ranges(x: float, y: float, heading: float) -> tuple[list[int], list[int]]:
    out = [sense_one(OCC, 10, 10, 500.0, x, y, heading, i, DEFAULT_TW) for i in range(robot_spec.SENSOR_COUNT)]
    return [int(r) for r, _ in out], [int(s) for _, s in out]


def _telemetry(t_ms: int, x: float, y: float, heading: float, ranges: list[int], status: list[int],
               layout: Layout | None = None) -> list:
    """LOCAL_POSITION_NED, ATTITUDE and OBSTACLE_DISTANCE of one robot tick, over the wire and back
    (the sensors of `layout`, a robot profile's, as its controller reports them; default the built-in)."""
    sensors = {} if layout is None else {"range_angles_mrad": layout.angles_mrad, "range_max_mm": layout.max_range_mm}
    st = VehicleStatus(x_mm=round(x), y_mm=round(y), heading_mrad=round(heading * 1000), ranges_mm=ranges,
                       range_status=status, **sensors)
    out = []
    for msg_id in (m.MAVLINK_MSG_ID_OBSTACLE_DISTANCE, m.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                   m.MAVLINK_MSG_ID_ATTITUDE):
        for msg in TEL.build(msg_id, t_ms * 1000, st, NodeStats()):
            out.append(MAV.parse_char(msg.pack(MAV)))
    return out


def _feed(f: MissionFollower, msgs: list) -> list:
    return [r for r in (f.handle(msg) for msg in msgs) if r is not None]


@pytest.mark.parametrize("pose", [(1250, 3750, 0.0), (2750, 2750, 1.2), (4750, 250, 2.6), (250, 4750, -0.7)])
def test_the_known_map_alone_is_never_an_obstacle(pose):
    f = MissionFollower(GM, [GM.targets["B"]], [3])
    for t in range(0, 2000, 100):  # the robot turning in place: walls seen at every angle
        x, y, h = pose[0], pose[1], pose[2] + t / 1000.0
        assert _feed(f, _telemetry(t, x, y, h, *_map_ranges(x, y, h))) == []
    assert f.seen is not None and f.seen.recent(2_000_000) == []


def test_a_reading_shorter_than_the_map_is_placed_where_it_was_seen():
    seen = UnmappedPoints(GM)
    x, y, h = 1250.0, 3750.0, 0.0
    ranges, status = _map_ranges(x, y, h)
    assert ranges[0] > 700  # the way east is open on the map
    ranges[0], status[0] = 300, robot_spec.RANGE_VALID  # something 300 mm ahead
    f = MissionFollower(GM, [GM.targets["B"]], [3], seen=seen)
    _feed(f, _telemetry(100, x, y, h, ranges, status) + _telemetry(200, x, y, h, ranges, status))
    pts = seen.recent(200_000)
    assert len(pts) == 2
    for px, py in pts:
        assert px == pytest.approx(x + robot_spec.SENSOR_MOUNT_RADIUS_MM + 300, abs=10) and py == pytest.approx(y, abs=1)


WIDE_SIX = load_profile(robot_spec.__file__.replace("robot_spec.py", "profiles/wide_six.toml")).layout()
OPEN = GridMap("open", np.zeros((10, 10), dtype=bool), {"B": (9, 0)})  # nothing within any sensor's reach of its middle


def _bearings(pts, x: float, y: float) -> list[tuple[float, float]]:
    """(bearing deg CCW from east in (-180, 180], distance mm) of each point from (x, y), sorted by bearing."""
    return sorted((180.0 - (180.0 - round(math.degrees(math.atan2(py - y, px - x)), 1)) % 360.0 + 0.0,
                   round(math.hypot(px - x, py - y))) for px, py in pts)


def test_each_reading_is_placed_at_the_profiles_sensor_angle():
    """`MissionFollower(layout=)` (`qnav mission upload --plan --follow --profile`): a wide_six robot's
    OBSTACLE_DISTANCE (its controller fills each sensor's cone at that sensor's angle) is read per
    wide_six sensor and placed at that sensor's angle on its 180 mm rim: the 40-deg sensor's reading at
    40 deg (the built-in layout reads the same bin as its 45-deg sensor, 5 deg off, on a 150 mm rim),
    and nothing where wide_six has no sensor (135 / -135 deg)."""
    x, y = 2500.0, 2500.0
    far, valid = robot_spec.RANGE_TOO_FAR, robot_spec.RANGE_VALID
    ranges, status = [1500] * 6, [far] * 6
    ranges[1], status[1] = 300, valid  # the 40-deg sensor sees something 300 mm off its rim
    msgs = _telemetry(100, x, y, 0.0, ranges, status, WIDE_SIX)
    f = MissionFollower(OPEN, [OPEN.targets["B"]], [0], radius_mm=180.0, layout=WIDE_SIX)
    _feed(f, msgs)
    assert f.seen is not None and _bearings(f.seen.recent(100_000), x, y) == [(40.0, 480)]
    old = MissionFollower(OPEN, [OPEN.targets["B"]], [0])  # the built-in layout: what the follower did for any robot
    _feed(old, msgs)
    assert old.seen is not None and _bearings(old.seen.recent(100_000), x, y) == [(45.0, 450)]

    f = MissionFollower(OPEN, [OPEN.targets["B"]], [0], radius_mm=180.0, layout=WIDE_SIX)
    _feed(f, _telemetry(200, x, y, 0.0, [300] * 6, [valid] * 6, WIDE_SIX))  # every sensor sees something
    assert f.seen is not None
    got = _bearings(f.seen.recent(200_000), x, y)
    assert got == [(-85.0, 480), (-50.0, 480), (0.0, 480), (40.0, 480), (95.0, 480), (180.0, 480)], got
    assert not any(abs(abs(b) - 135.0) < 22.5 for b, _ in got)
    bins = list(range(100, 172))  # each bin's own value: the bin on each wide_six sensor's axis
    assert sensor_readings(bins, 5.0, 0.0, 2, 200, WIDE_SIX) == [1000, 1640, 1100, 1530, 1170, 1360]


def test_the_built_in_layout_places_its_eight_readings_as_before():
    """Without a profile the follower reads and places the built-in robot's eight sensors as it did."""
    x, y = 2500.0, 2500.0
    f = MissionFollower(OPEN, [OPEN.targets["B"]], [0])
    _feed(f, _telemetry(100, x, y, 0.0, [300] * 8, [robot_spec.RANGE_VALID] * 8))
    assert f.seen is not None
    assert _bearings(f.seen.recent(100_000), x, y) == [(-135.0, 450), (-90.0, 450), (-45.0, 450), (0.0, 450),
                                                       (45.0, 450), (90.0, 450), (135.0, 450), (180.0, 450)]
    bins = list(range(100, 172))  # each bin's own value: which bin each sensor is read from
    assert sensor_readings(bins, 5.0, 0.0, 2, 200) == [1000, 1630, 1540, 1450, 1360, 1270, 1180, 1090]


def test_a_reading_at_its_sensors_own_reach_is_no_point():
    """A sensor of shorter reach than the others (`sensors.max_ranges_mm`): its reading at that reach
    (no echo; OBSTACLE_DISTANCE's max_distance is the farthest sensor's) is no obstacle."""
    from dataclasses import replace

    lay = replace(WIDE_SIX, max_ranges_mm=(1500, 400, 1500, 1500, 1500, 1500))
    x, y = 2500.0, 2500.0
    for d, n in ((400, 0), (390, 1)):
        ranges, status = [1500] * 6, [robot_spec.RANGE_TOO_FAR] * 6
        ranges[1], status[1] = d, robot_spec.RANGE_VALID
        f = MissionFollower(OPEN, [OPEN.targets["B"]], [0], radius_mm=180.0, layout=lay)
        _feed(f, _telemetry(100, x, y, 0.0, ranges, status, lay))
        assert f.seen is not None and len(f.seen.recent(100_000)) == n, d


def _stalled_before_a_disc(f: MissionFollower, disc=(3100.0, 4300.0, 150.0), pose=(2759.0, 4218.0, 1.07)) -> None:
    """Scans of a robot dithering in front of a disc: the front and front-right sensors see it."""
    x, y, h0 = pose
    for t in range(0, 3000, 100):
        h = h0 + 0.05 * math.sin(t / 300.0)
        ranges, status = _map_ranges(x, y, h)
        for i in range(robot_spec.SENSOR_COUNT):  # the disc: a ray from the mount along the axis
            a = h + robot_spec.SENSOR_ANGLES_MRAD[i] / 1000.0
            ox, oy = x + 150 * math.cos(a), y + 150 * math.sin(a)
            dx, dy = disc[0] - ox, disc[1] - oy
            along = dx * math.cos(a) + dy * math.sin(a)
            miss = abs(-dx * math.sin(a) + dy * math.cos(a))
            if along > 0 and miss < disc[2]:
                d = along - math.sqrt(disc[2] ** 2 - miss ** 2)
                if status[i] != robot_spec.RANGE_VALID or d < ranges[i]:
                    ranges[i], status[i] = round(d), robot_spec.RANGE_VALID
        _feed(f, _telemetry(t, x, y, h, ranges, status))


def _item_mm(item: tuple[int, int, int]) -> tuple[float, float]:
    return item[2] * 1000 / LOCAL_ITEM_SCALE, item[1] * 1000 / LOCAL_ITEM_SCALE  # east, north


def test_a_stall_replans_round_the_obstacle_and_the_last_target_finishes():
    disc = (3100.0, 4300.0, 150.0)
    f = MissionFollower(GM, [GM.targets["A"], GM.targets["B"]], [2, 6])
    assert _feed(f, [m.MAVLink_mission_item_reached_message(2)]) == []  # A reached
    _stalled_before_a_disc(f, disc)
    out = f.text("item 2: no progress for 10 s, 724 mm to go")
    assert isinstance(out, Replan), out
    path = [(2759.0, 4218.0)] + [_item_mm(it) for it in out.items]
    bx, by = (9 + 0.5) * 500, (10 - 0 - 0.5) * 500
    assert math.dist(path[-1], (bx, by)) < 1 and out.target_seq == [len(out.items) - 1]
    assert all(math.dist(a, b) <= 1000 + 1 for a, b in zip(path[1:], path[2:], strict=False))
    for (ax, ay), (qx, qy) in zip(path[1:], path[2:], strict=False):  # every leg after the first step clears the disc
        t = np.linspace(0.0, 1.0, 50)
        gap = np.hypot(ax + t * (qx - ax) - disc[0], ay + t * (qy - ay) - disc[1]).min() - disc[2]
        assert gap >= robot_spec.ROBOT_RADIUS_MM, (gap, path)
    assert f.handle(m.MAVLink_mission_item_reached_message(len(out.items) - 2)) is None
    done = f.handle(m.MAVLink_mission_item_reached_message(len(out.items) - 1))
    assert isinstance(done, Finished) and done.ok and "1 re-plan" in done.text


def _replan_clearance(radius_mm: float | None) -> tuple[float, list[tuple[float, float]]]:
    """The smallest distance (mm) from the legs of the re-plan round the disc (after the first
    step out of the margin) to the points the follower saw, and the re-plan's path."""
    disc = (3100.0, 4300.0, 150.0)
    kw = {} if radius_mm is None else {"radius_mm": radius_mm}
    f = MissionFollower(GM, [GM.targets["A"], GM.targets["B"]], [2, 6], **kw)
    _feed(f, [m.MAVLink_mission_item_reached_message(2)])
    _stalled_before_a_disc(f, disc)
    assert f.seen is not None
    pts = np.array(f.seen.recent(3_000_000))
    out = f.text("item 2: no progress for 10 s, 724 mm to go")
    assert isinstance(out, Replan), out
    path = [(2759.0, 4218.0)] + [_item_mm(it) for it in out.items]
    t = np.linspace(0.0, 1.0, 200)[:, None]
    gap = min(float(np.hypot(ax + t * (qx - ax) - pts[None, :, 0], ay + t * (qy - ay) - pts[None, :, 1]).min())
              for (ax, ay), (qx, qy) in zip(path[1:], path[2:], strict=False))
    return gap, path


def test_a_replan_keeps_the_profiles_body_clear_of_what_was_seen():
    """`MissionFollower(radius_mm=)` (`qnav mission upload --plan --follow --profile`): the re-plan keeps
    the profile's body + 75 mm off the unmapped points (each a 25 mm disc), where the built-in robot's
    re-plan keeps its own 150 mm body clear and passes too close for a 180 mm one."""
    need = 75.0 + 25.0 - 5.0  # the raster's margin + the point's disc, less the 50 mm raster's slack
    built_in, built_in_path = _replan_clearance(None)
    wide, wide_path = _replan_clearance(180.0)
    # measured: 249 mm for the built-in (150 + 100 needed), 290 mm for the 180 mm body
    assert built_in >= robot_spec.ROBOT_RADIUS_MM + need and built_in < 180.0 + need
    assert wide >= 180.0 + need and wide_path != built_in_path
    assert _replan_clearance(float(robot_spec.ROBOT_RADIUS_MM)) == (built_in, built_in_path)


def test_a_wider_body_still_replans_through_one_cell_corridors():
    """The map's walls keep the body + 75 mm clear only down to what a 500 mm corridor leaves on the
    raster: a 180 or 200 mm body (70 or 50 mm each side there) is still planned through paper10's
    one-cell corridors, which its planned route takes (without that: 11 of these 296 legs planned)."""
    c = 500.0
    free = [(col, row) for row in range(10) for col in range(10) if not GM.occ[row][col]]
    for radius in (150.0, 180.0, 200.0):
        n = 0
        for target in GM.targets.values():
            for s in free:
                if s != target:
                    raster_plan(GM, [], ((s[0] + 0.5) * c, (9.5 - s[1]) * c),
                                [((target[0] + 0.5) * c, (9.5 - target[1]) * c)], radius_mm=radius)
                    n += 1
        assert n == 296
    with pytest.raises(MapError, match="no path"):  # a body wider than the corridor is not
        raster_plan(GM, [], (250.0, 4750.0), [(250.0, 250.0)], radius_mm=260.0)


def test_a_stall_with_nothing_unmapped_in_view_gives_up_with_a_reason():
    f = MissionFollower(GM, [GM.targets["B"]], [3])
    assert isinstance(f.text("no progress for 10 s"), Finished)  # no pose yet
    x, y, h = 1250.0, 3750.0, 0.0
    _feed(f, _telemetry(0, x, y, h, *_map_ranges(x, y, h)) + _telemetry(100, x, y, h, *_map_ranges(x, y, h)))
    out = f.text("item 0: no progress for 10 s, 3000 mm to go")
    assert isinstance(out, Finished) and not out.ok and "nothing the map does not" in out.text
    assert f.text("reached item 0") is None


def test_no_path_left_is_a_map_error():
    ring = [(1250.0 + 350 * math.cos(k / 20), 3750.0 + 350 * math.sin(k / 20)) for k in range(126)]
    assert len(raster_plan(GM, [], (1250.0, 3750.0), [(4750.0, 4750.0)])[0]) >= 2  # open without the ring
    with pytest.raises(MapError, match="no path"):
        raster_plan(GM, ring, (1250.0, 3750.0), [(4750.0, 4750.0)])


@pytest.mark.parametrize("argv, says", [
    (["mission", "upload", "--targets", "A", "--follow"], "--follow needs --plan"),
    (["mission", "upload", "--targets", "A", "--plan", "--follow", "--follow-timeout", "0"], "--follow-timeout"),
    (["mission", "upload", "--targets", "A", "--plan", "--follow", "--follow-timeout", "nan"], "--follow-timeout"),
])
def test_follow_bad_arguments_are_refused_with_one_line(argv, says):
    code, err = _run(*argv)
    assert code == 2 and says in err, err
    assert "Traceback" not in err
