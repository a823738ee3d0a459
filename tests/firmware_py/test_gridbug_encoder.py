"""The cell-stepped Bug memory encoder (`firmware_py.kinds.sector_memory.gridbug`): the mode rules,
the state layout, the neighbour flags from the sensors, and its .qtab kind
(round trip, damaged sections refused with one line)."""

from __future__ import annotations

import struct
import zlib
from array import array

import pytest

from firmware_py import kinds, robot_spec
from firmware_py.kinds.sector_memory.gridbug import (
    MODE_GO,
    MODE_WALL_LEFT,
    MODE_WALL_RIGHT,
    MOVE_BACK,
    MOVE_FORWARD,
    MOVE_LEFT,
    MOVE_RIGHT,
    N_FREE,
    N_SECTORS,
    GridBugEncoder,
    GridBugMemory,
    grid_dir_of,
    rotate_into,
)
from firmware_py.policy import (
    MapGeometry,
    PolicyError,
    config_mismatch,
    dump_policy,
    load_policy,
)

C = 500
ALL = 0b1111
E, N, W, S = 1, 2, 4, 8  # world free bits


def test_grid_direction_and_rotation():
    assert [grid_dir_of(h) for h in (0, 700, 900, 1571, 3142, -1571, -3000, 6283)] == [0, 0, 1, 1, 2, 3, 2, 0]
    # the goal 2 cells north seen facing north is ahead, facing east it is to the left
    assert rotate_into(0, 1000, 1) == (1000, 0)
    assert rotate_into(0, 1000, 0) == (0, 1000)
    assert rotate_into(0, 1000, 2) == (0, -1000)
    assert rotate_into(0, 1000, 3) == (-1000, 0)


def test_sectors_are_the_goalward_moves():
    enc = GridBugEncoder()
    mem = GridBugMemory()
    # facing east, goal 3 east 2 north: ahead-left (sector 1), every neighbour free
    assert enc.encode_free(mem, 3 * C, 2 * C, ALL) == 1 * N_FREE + ALL
    # less than half a cell off the axis is "ahead" (a sideways move would not bring the robot closer)
    assert enc.encode_free(mem, 3 * C, C // 2, ALL) == 0 * N_FREE + ALL
    assert enc.encode_free(mem, 3 * C, C // 2 + 1, ALL) == 1 * N_FREE + ALL
    assert enc.goalward_mask(-C, -C, 0) == W | S
    # facing south, the goal to the east is to the left
    mem.reset(3)
    assert enc.encode_free(mem, 4 * C, 0, ALL) == 2 * N_FREE + ALL
    assert mem.mode == MODE_GO


def test_hit_picks_the_side_once_and_turns_the_frame():
    enc = GridBugEncoder()
    mem = GridBugMemory()
    mem.reset(0)  # facing east, goal 4 east 1 north, east and north blocked: hit
    s = enc.encode_free(mem, 4 * C, C, W | S)
    assert mem.mode == MODE_WALL_RIGHT and mem.side == MODE_WALL_RIGHT  # goal to the left: wall on the right
    assert mem.hit_mm == 2061  # isqrt(2000^2 + 500^2)
    # the first goal-ward direction (east) is put on the right: facing north
    assert mem.heading == 1
    # wall state: free bits relative to north: front (N) blocked, left (W), back (S) free, right (E) blocked
    assert s == N_SECTORS * N_FREE + (1 << MOVE_LEFT | 1 << MOVE_BACK)
    # not closer than the hit: stays on the wall even with a goal-ward cell free
    mem.note_move(MOVE_LEFT)
    assert enc.update(mem, 5 * C, C, ALL) == MODE_WALL_RIGHT
    # closer by >= the margin with a goal-ward neighbour free: back to go
    assert enc.update(mem, 4 * C, 0, E | W) == MODE_GO
    # a new hit keeps the side chosen first, although the goal is now to the right
    mem.reset(0)
    mem.side = MODE_WALL_RIGHT
    enc.update(mem, 4 * C, -C, W | N)
    assert mem.mode == MODE_WALL_RIGHT


def test_goal_to_the_right_follows_the_left_wall():
    enc = GridBugEncoder()
    mem = GridBugMemory()
    mem.reset(0)
    enc.encode_free(mem, 4 * C, -2 * C, W | N)
    assert mem.mode == MODE_WALL_LEFT and mem.heading == 3  # east on the left: facing south


def test_wall_bearing_layout_and_sizes():
    assert GridBugEncoder().n_states == 128 + 2 * 16
    enc = GridBugEncoder(wall_bearing=True)
    assert enc.n_states == 128 * 3 and enc.n_actions == 4
    mem = GridBugMemory()
    mem.reset(0)
    s = enc.encode_free(mem, 4 * C, C, W | S)  # hit as above; facing north the goal is ahead-right (sector 7)
    assert s == N_SECTORS * N_FREE + 7 * N_FREE + (1 << MOVE_LEFT | 1 << MOVE_BACK)


def test_free_flags_from_the_sensors():
    enc = GridBugEncoder(free_mm=350)
    ranges = [100] * robot_spec.SENSOR_COUNT
    status = [robot_spec.RANGE_VALID] * robot_spec.SENSOR_COUNT
    ranges[0] = 600  # ahead of the robot
    status[4] = robot_spec.RANGE_TOO_FAR  # behind
    status[6] = robot_spec.RANGE_INVALID  # right: not seen -> blocked
    # robot physically facing north (1): ahead is north, behind south
    assert enc.free_mask(1, 0, ranges, status) == N | S
    # relative to a reference heading of north: front and back free
    assert enc.free_mask(1, 1, ranges, status) == (1 << MOVE_FORWARD | 1 << MOVE_BACK)
    # relative to a reference heading of east: north is left, south right
    assert enc.free_mask(1, 0, ranges, status) == (1 << MOVE_LEFT | 1 << MOVE_RIGHT)
    assert enc.free_mask(0, 0, ranges, status) == E | W
    ranges[0], status[0] = 349, robot_spec.RANGE_VALID
    assert enc.free_mask(0, 0, ranges, status) == W
    status[0] = robot_spec.RANGE_TOO_CLOSE
    assert enc.free_mask(0, 0, [2000] * 8, status) == N | W  # too close ahead: blocked; right invalid: blocked


def test_invalid_encoders_refused():
    with pytest.raises(ValueError, match="free_mm"):
        GridBugEncoder(free_mm=5)
    with pytest.raises(ValueError, match="leave_margin_mm"):
        GridBugEncoder(leave_margin_mm=-1)
    with pytest.raises(ValueError, match="cell_mm"):
        GridBugEncoder(cell_mm=0)


def _table(enc: GridBugEncoder, move: int) -> array:
    vals = array("b")
    for _ in range(enc.n_states):
        vals.extend(100 if i == move else 0 for i in range(enc.n_actions))
    return vals


def test_qtab_round_trip_and_bad_sections():
    enc = GridBugEncoder(free_mm=300, leave_margin_mm=7, wall_bearing=True)
    data = dump_policy(enc, _table(enc, MOVE_RIGHT), "int8", 0.01, map_geometry=MapGeometry(500, 10, 10))
    pol = load_policy(data)
    assert pol.kind == "sector-memory" and pol.encoder == enc and pol.n_states == enc.n_states
    assert pol.best_action(5) == MOVE_RIGHT and pol.header()["encoder"]["leave_margin_mm"] == 7
    assert config_mismatch(pol, robot_spec.CONTROL_PERIOD_US, 500) == ""
    assert config_mismatch(pol, robot_spec.CONTROL_PERIOD_US, 400) == "policy cell size 500 mm != robot 400 mm"
    head = 58

    def patched(off: int, value: bytes) -> bytes:
        b = bytearray(data[:-4])
        b[off:off + len(value)] = value
        return bytes(b) + struct.pack("<I", zlib.crc32(bytes(b)))

    assert data[12] == kinds.of_name("sector-memory").code == 4
    with pytest.raises(PolicyError, match="wall_bearing 2"):
        load_policy(patched(head + 6, b"\x02"))
    with pytest.raises(PolicyError, match="free_mm must be in"):
        load_policy(patched(head, struct.pack("<H", 5)))
    with pytest.raises(PolicyError, match="action set"):
        load_policy(patched(head + 7, struct.pack("<hh", 0, 1)))
    with pytest.raises(PolicyError, match="sector encoder section is"):
        load_policy(patched(12, b"\x02"))  # declared a plain sector policy
    with pytest.raises(ValueError, match="table has"):
        dump_policy(enc, _table(GridBugEncoder(), MOVE_BACK), "int8", 0.01, map_geometry=MapGeometry(500, 10, 10))


def test_note_move_turns_the_reference_heading():
    mem = GridBugMemory()
    mem.reset(3)
    assert mem.note_move(MOVE_LEFT) == 0 and mem.note_move(MOVE_BACK) == 2 and mem.note_move(MOVE_FORWARD) == 2
    assert mem.mode == MODE_GO


def test_qnav_robot_takes_the_cell_size_from_a_sector_memory_policy():
    """qnav-robot steps on the policy's grid unless --cell-size says otherwise
    (a 400 mm policy is not refused for the 500 mm default)."""
    from firmware_py import cli

    enc = GridBugEncoder(cell_mm=400)
    pol = load_policy(dump_policy(enc, _table(enc, MOVE_FORWARD), "int8", 0.01, map_geometry=MapGeometry(400, 10, 10)))
    args = cli.build_parser().parse_args(["--can", "virtual:x"])
    assert cli._policy_cell_mm(args, pol) == 400
    assert config_mismatch(pol, robot_spec.CONTROL_PERIOD_US, cli._policy_cell_mm(args, pol)) == ""
    args = cli.build_parser().parse_args(["--can", "virtual:x", "--cell-size", "0.5"])
    assert config_mismatch(pol, robot_spec.CONTROL_PERIOD_US, cli._policy_cell_mm(args, pol)) \
        == "policy cell size 400 mm != robot 500 mm"
