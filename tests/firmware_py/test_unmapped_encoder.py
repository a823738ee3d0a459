"""The `sector-unmapped` reference encoder (firmware_py/unmapped.py): which
readings the map explains (a map wall, also from a pose a little off, and a
grazed corner) and which it does not (a disc in the open), the go rows
equal the plain sector state, the detour's entry, side, hysteresis and leave
rules, and the no-map fallback."""

from __future__ import annotations

import pytest

from firmware_py import robot_spec
from firmware_py.encoders import TURN_LEFT, SectorEncoder
from firmware_py.mapdata import grid_from_rows
from firmware_py.unmapped import (
    KEEP_LEFT,
    KEEP_RIGHT,
    REJOIN_LEAVE_MM,
    DetourMemory,
    UnmappedSectorEncoder,
    unmapped_readings,
)

V, CLOSE, FAR = robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_CLOSE, robot_spec.RANGE_TOO_FAR
# 6 x 5 cells of 500 mm, a wall column at col 4 (x 2000..2500 mm) with the map's border around
GRID = grid_from_rows(["......", "....@.", "....@.", "....@.", "......"], 500)
ENC = UnmappedSectorEncoder()


def test_a_map_wall_is_explained_a_disc_in_the_open_is_not():
    # robot at x 1500 facing east (heading 0): front sensor's mount at x 1650, the wall's face at x 2000
    ranges = [350] + [2000] * 7
    status = [V] + [FAR] * 7
    assert unmapped_readings(GRID, 1500, 1250, 0, ranges, status, 150)[0] == -1
    # the same reading 100 mm off in x (the localiser's corridor error) is still the wall
    assert unmapped_readings(GRID, 1400, 1250, 0, ranges, status, 150)[0] == -1
    # a reading of 200 mm ends 150 mm short of the wall (within the margin); 190 mm ends 160 short: a disc
    ranges[0] = 200
    assert unmapped_readings(GRID, 1500, 1250, 0, ranges, status, 150)[0] == -1
    ranges[0] = 190
    assert unmapped_readings(GRID, 1500, 1250, 0, ranges, status, 150)[0] == 190
    # too far never counts; too close in the open is an unmapped contact (distance 0)
    assert unmapped_readings(GRID, 1500, 1250, 0, [20] + [2000] * 7, [CLOSE] + [FAR] * 7, 150)[0] == 0
    assert all(d == -1 for d in unmapped_readings(GRID, 1500, 1250, 0, [2000] * 8, [FAR] * 8, 150))


def test_the_outer_border_and_a_grazed_corner_are_explained():
    # facing north from (750, 2000): the border (y 2500) 500 - 150 = 350 mm from the front sensor
    um = unmapped_readings(GRID, 750, 2000, 1571, [350] + [0] * 7, [V] + [FAR] * 7, 150)
    assert um[0] == -1
    # heading at the wall block's south-west corner (2000, 1000) from (1600, 700): a reading ending at the corner
    um = unmapped_readings(GRID, 1600, 700, 644, [350] + [0] * 7, [V] + [FAR] * 7, 150)
    assert um[0] == -1


def test_go_rows_are_the_sector_state_and_no_map_means_go_rows():
    base = SectorEncoder(15, (0, 1, 7), (100, 400))
    mem = DetourMemory()
    ranges, status = [120, 300, 900, 2000, 80, 500, 60, 1000], [V] * 8
    for b in range(-3141, 3142, 97):
        want = base.encode(b, ranges, status)
        assert ENC.encode(mem, b, 3000, ranges, status, None) == want  # no map
        assert ENC.encode(mem, b, 3000, ranges, status, [-1] * 8) == want  # nothing unmapped
        assert not mem.detour
    assert ENC.n_go == base.n_states and ENC.n_states == base.n_states + 2 * 3 * 8 * 4 ** 5


def test_detour_entry_side_hysteresis_and_leave():
    enc = UnmappedSectorEncoder(leave_margin_mm=100)
    mem = DetourMemory()
    ranges = [250, 1500, 1500, 2000, 2000, 2000, 300, 400]  # free on the left, closer on the right
    status = [V] * 8
    um = [250] + [-1] * 7  # an unmapped obstacle 250 mm ahead, waypoint straight ahead 1000 mm away
    s = enc.encode(mem, 0, 1000, ranges, status, um)
    assert mem.detour and mem.side == KEEP_RIGHT and mem.hit_mm == 1000  # go round it on the left
    assert s >= enc.n_go
    mem.note_action(1)  # turn left
    assert mem.last_turn == TURN_LEFT
    # turned away in place: the obstacle now on the right diagonal (kept side), the waypoint no closer
    beside = [-1] * 7 + [260]
    s2 = enc.encode(mem, -700, 1000, ranges, status, beside)
    assert mem.detour and s2 >= enc.n_go + enc.code_states * 8  # last turn left: the second block
    # the waypoint ahead-right still has the obstacle in its way: blocked, whatever the distance
    enc.encode(mem, -785, 500, ranges, status, beside)
    assert mem.detour
    # closer by more than the leave margin and the way clear, the obstacle still beside -> go
    side_only = [-1] * 6 + [200, -1]
    assert enc.encode(mem, 300, 850, ranges, status, side_only) < enc.n_go and not mem.detour
    # again blocked: the side is kept; passed (nothing unmapped on the kept side, way clear) -> go
    enc.encode(mem, 0, 800, ranges, status, [150] + [-1] * 7)
    assert mem.detour and mem.side == KEEP_RIGHT and mem.hit_mm == 800
    assert enc.encode(mem, 0, 800, ranges, status, [-1] * 8) < enc.n_go and not mem.detour
    # an obstacle beyond the waypoint does not block
    mem.reset()
    enc.encode(mem, 0, 200, ranges, status, um)
    assert not mem.detour
    # the side: round the side the obstacle is not on, else the side with more room; reset() forgets it
    mem.reset()
    ranges_r = [250, 300, 300, 2000, 2000, 2000, 1500, 1500]
    enc.encode(mem, 0, 1000, ranges_r, status, um)
    assert mem.side == KEEP_LEFT
    mem.reset()
    enc.encode(mem, 0, 1000, ranges_r, status, [250, -1, -1, -1, -1, -1, -1, 300])  # obstacle seen on the right
    assert mem.side == KEEP_RIGHT
    # leave 0: the detour lasts until the next waypoint
    stay = UnmappedSectorEncoder(leave=0)
    mem.reset()
    stay.encode(stay_mem := mem, 0, 1000, ranges, status, um)
    assert stay.encode(stay_mem, 0, 100, ranges, status, [-1] * 8) >= stay.n_go and stay_mem.detour


def test_detour_codes_tell_a_disc_from_a_wall():
    stay = UnmappedSectorEncoder(leave=0)  # the detour holds whatever is seen
    mem = DetourMemory(detour=True, side=KEEP_RIGHT, hit_mm=0)
    ranges, status = [300, 2000, 2000, 2000, 2000, 2000, 2000, 2000], [V] + [FAR] * 7
    disc = stay.encode(mem, 0, 4000, ranges, status, [300] + [-1] * 7)
    wall = stay.encode(mem, 0, 4000, ranges, status, [-1] * 8)
    assert disc != wall and ENC.n_go <= min(disc, wall) and max(disc, wall) < ENC.n_states
    assert ENC.code(0, ranges, status, [300] + [-1] * 7) == 1 and ENC.code(0, ranges, status, [-1] * 8) == 2


def test_a_detour_that_gets_no_nearer_switches_side_and_a_dither_rejoins():
    enc = UnmappedSectorEncoder(switch_ticks=3, rejoin=1)
    mem = DetourMemory()
    ranges, status = [250, 1500, 1500, 2000, 2000, 2000, 300, 400], [V] * 8
    um = [250] + [-1] * 7
    enc.encode(mem, 0, 1000, ranges, status, um)
    assert mem.detour and mem.side == KEEP_RIGHT
    for _ in range(3):  # three ticks no nearer than 1000 mm, still blocked
        enc.encode(mem, 0, 1000, ranges, status, um)
    assert mem.side == KEEP_LEFT and mem.stall == 0 and mem.best_mm == 1000
    enc.encode(mem, 0, 990, ranges, status, um)
    assert mem.best_mm == 990 and mem.stall == 0
    # passed: go; then the go rows turn left, right: a dither enters the detour rows again ...
    enc.encode(mem, 0, 990, ranges, status, [-1] * 8)
    assert not mem.detour
    mem.note_action(1)
    mem.note_action(2)
    assert enc.encode(mem, 0, 990, ranges, status, [-1] * 8) >= enc.n_go and mem.detour and mem.rejoined
    # ... which ends only REJOIN_LEAVE_MM nearer the waypoint
    enc.encode(mem, 0, 900, ranges, status, [-1] * 8)
    assert mem.detour
    enc.encode(mem, 0, 989 - REJOIN_LEAVE_MM, ranges, status, [-1] * 8)
    assert not mem.detour
    # no dither before a detour of this waypoint (side not chosen): the go rows stay in charge
    mem.reset()
    mem.note_action(1)
    mem.note_action(2)
    assert enc.encode(mem, 0, 990, ranges, status, [-1] * 8) < enc.n_go


@pytest.mark.parametrize("kw", [{"detour_sensors": ()}, {"detour_sensors": (0, 8)}, {"detour_sensors": (1, 1)},
                                {"margin_mm": -1}, {"block_mm": 0}, {"block_bearing_mrad": 4000},
                                {"leave_margin_mm": -5}, {"range_edges_mm": (400, 100)}, {"leave": 2},
                                {"clear_mm": -1}, {"switch_ticks": -1}, {"rejoin": 3}])
def test_bad_parameters_are_refused(kw):
    with pytest.raises(ValueError):
        UnmappedSectorEncoder(**kw)
