"""The obstacle memory and the blind gaps between the sensor cones (firmware_py/kinds/sector/memory.py,
`ObstacleMemory._no_room`): a remembered point near the rim where no body of `MIN_BODY_RADIUS_MM`
could stand unseen is cleared, pinned or not (before, a point outside every cone stayed while pinned:
the demo's stall at a corridor's exit, tests/hil/test_phantom_point_hil.py); a real disc's point
there stays (the disc is read), and so does a point farther out, where a body fits in the gap."""

from __future__ import annotations

import math

from firmware_py import robot_spec
from firmware_py.kinds.sector.memory import MIN_BODY_RADIUS_MM, ObstacleMemory
from firmware_py.mapdata import grid_from_rows
from tests.support.localplan_rig import CFG, FAR, N, V

GRID = grid_from_rows(["." * 10] * 10, 500)  # open, 5 x 5 m
X, Y = 2500, 2500  # the robot, facing east (heading 0)
R = robot_spec.ROBOT_RADIUS_MM


def _at(dist: float, deg: float) -> tuple[int, int]:
    a = math.radians(deg)
    return round(X + dist * math.cos(a)), round(Y + dist * math.sin(a))


def _pinned(*pts: tuple[int, int]) -> ObstacleMemory:
    mem = ObstacleMemory(CFG)
    for x, y in pts:
        mem.points[(x // 50, y // 50)] = (x, y, 0)
    mem.pin(0)
    return mem


def _readings(disc: tuple[float, float, float] | None) -> tuple[list[int], list[int]]:
    """What the sim's fans (three rays a cone, from the robot's centre) read of one disc in the open."""
    ranges, status = [robot_spec.RANGE_MAX_MM] * N, [FAR] * N
    if disc is None:
        return ranges, status
    cx, cy, r = disc
    half = robot_spec.SENSOR_FOV_MRAD / 2000.0
    for i, a in enumerate(robot_spec.SENSOR_ANGLES_MRAD):
        best = math.inf
        for d in (-half, 0.0, half):
            ux, uy = math.cos(a / 1000 + d), math.sin(a / 1000 + d)
            t = (cx - X) * ux + (cy - Y) * uy
            off2 = (cx - X - t * ux) ** 2 + (cy - Y - t * uy) ** 2
            if t > 0 and off2 < r * r:
                best = min(best, t - math.sqrt(r * r - off2))
        if best - R < robot_spec.RANGE_MAX_MM:
            ranges[i], status[i] = round(best - R), V
    return ranges, status


def test_a_point_in_the_gap_by_the_rim_with_nothing_read_there_is_cleared():
    phantom = _at(R + 40, -30)  # between the front and front-right cones, 40 mm off the rim
    mem = _pinned(phantom)
    mem.observe(GRID, X, Y, 0, *_readings(None), 100_000)
    assert not mem.points  # before: kept while pinned (no cone holds it, so no reading saw through it)


def test_a_disc_read_in_the_gap_keeps_its_point():
    point = _at(R + 40, -30)
    r = MIN_BODY_RADIUS_MM + 20
    cx, cy = _at(R + 40 + r, -30)  # the disc beyond the point: the front and front-right sensors read it
    ranges, status = _readings((cx, cy, r))
    assert status[0] == V and status[N - 1] == V
    mem = _pinned(point)
    mem.observe(GRID, X, Y, 0, ranges, status, 100_000)
    assert (point[0] // 50, point[1] // 50) in mem.points


def test_a_point_in_the_gap_farther_out_stays_pinned():
    far = _at(R + 450, -22)  # a body fits between the cones out there
    mem = _pinned(far)
    mem.observe(GRID, X, Y, 0, *_readings(None), 100_000)
    assert (far[0] // 50, far[1] // 50) in mem.points


def test_the_nearest_sensor_lookup_answers_as_a_scan_of_every_direction():
    """`_seen_through` finds each point's cone by the sorted directions' two neighbours (a scan of
    every direction per point was a third of the tick's memory update): the same index for every
    angle, ties to the lowest index, on the built-in eight and on uneven layouts."""
    import random

    from firmware_py.kinds.sector.memory import _circular_order, _nearest_sensor

    rng = random.Random(0)
    layouts = [[a / 1000.0 for a in robot_spec.SENSOR_ANGLES_MRAD], [-1.2, 0.0, 1.2, 3.1416, -0.4, 0.4],
               [0.0, math.pi / 2, math.pi, -math.pi / 2], [2.5, -2.5, 0.0]]
    for ang in layouts:
        order = _circular_order(ang)
        probes = [rng.uniform(-4 * math.pi, 4 * math.pi) for _ in range(3000)]
        probes += [a + d for a in ang for d in (0.0, 1e-9, -1e-9, math.pi, 2 * math.pi)]
        probes += [(ang[i] + ang[j]) / 2 for i in range(len(ang)) for j in range(len(ang))]  # midpoints: ties
        for rel in probes:
            scan = min(range(len(ang)), key=lambda j: abs((rel - ang[j] + math.pi) % (2 * math.pi) - math.pi))
            assert _nearest_sensor(rel, ang, order) == scan, (ang, rel)
