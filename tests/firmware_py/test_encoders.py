"""Reference encoders: hand-checked values."""

import pytest

from firmware_py import robot_spec
from firmware_py.kinds.base import best_action
from firmware_py.kinds.cell.encoder import CellEncoder
from firmware_py.kinds.sector.encoder import SectorEncoder, bearing_sector


def test_bearing_sector_is_centred_straight_ahead_and_counts_ccw():
    assert bearing_sector(0, 8) == 0
    assert bearing_sector(392, 8) == 0  # just under 22.5 deg
    assert bearing_sector(393, 8) == 1
    assert bearing_sector(1571, 8) == 2  # 90 deg left
    assert bearing_sector(-1571, 8) == 6  # 90 deg right
    assert bearing_sector(3142, 8) == 4
    assert bearing_sector(-392, 8) == 0
    assert bearing_sector(-394, 8) == 7


def test_sector_state_layout():
    enc = SectorEncoder(bearing_sectors=4, sensors=(0, 2), range_edges_mm=(500,))
    ranges = [100] * robot_spec.SENSOR_COUNT
    assert enc.n_states == 4 * 2 * 2
    assert enc.encode(0, ranges) == 0
    ranges[2] = 900
    assert enc.encode(0, ranges) == 2
    assert enc.encode(1571, ranges) == 1 * 4 + 2
    status = [robot_spec.RANGE_VALID] * robot_spec.SENSOR_COUNT
    status[0] = robot_spec.RANGE_TOO_FAR
    assert enc.encode(0, ranges, status) == 3


def test_cell_encoder_and_bounds():
    enc = CellEncoder(10, 10, 4)
    assert enc.encode(3, 2, 1) == 100 + 23
    assert enc.n_states == 400
    with pytest.raises(ValueError):
        enc.encode(10, 0, 0)


def test_best_action_breaks_ties_low():
    assert best_action([1, 5, 5, 2]) == 1
    assert best_action([-3, -3, -3, -3]) == 0
    assert best_action([0, 0, 0, 7]) == 3


def test_sim_clock_is_monotonic():
    from firmware_py.clock import SimClock
    from tests.support.sim_time import advance_us, wait_until

    c = SimClock()
    c.set_us(500)
    c.set_us(100)
    assert c.now_us() == 500
    advance_us(c, 50)
    assert c.now_us() == 550
    assert wait_until(c, 550, timeout_s=0.01)
    assert not wait_until(c, 10_000, timeout_s=0.01)
