"""The sector-memory reference encoder (`firmware_py.encoders.MemorySectorEncoder`
with its `BugMemory`): the mode rules, the state layout, its `.qtab` kind,
and the controller keeping and resetting the memory per goal."""

from array import array

import pytest

from firmware_py import robot_spec
from firmware_py.control.controller import Controller
from firmware_py.encoders import (
    MODE_GO,
    MODE_WALL_LEFT,
    MODE_WALL_RIGHT,
    TURN_RIGHT,
    BugMemory,
    MemorySectorEncoder,
)
from firmware_py.policy import PolicyError, dump_policy, load_policy
from firmware_py.vehicle import CtrlState, VehicleConfig
from tests.support.controller_rig import SECTOR_TRAINING_MAP, Kinematic, Rig

V, CLOSE, FAR = robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_CLOSE, robot_spec.RANGE_TOO_FAR
N = robot_spec.SENSOR_COUNT


def _ranges(front: int) -> tuple[list[int], list[int]]:
    r = [2000] * N
    st = [FAR] * N
    r[0], st[0] = front, V
    return r, st


def test_go_until_blocked_ahead_then_side_from_bearing_and_kept():
    enc = MemorySectorEncoder()
    mem = BugMemory()
    free, free_st = _ranges(1500)
    assert enc.update(mem, 0, 3000, free, free_st) == MODE_GO
    wall, wall_st = _ranges(enc.block_mm - 1)
    # blocked, but the goal is behind: the wall is not in the way
    assert enc.update(mem, 2000, 3000, wall, wall_st) == MODE_GO
    # blocked with the goal ahead-left: keep the wall on the right, remember where it was hit
    assert enc.update(mem, 300, 3000, wall, wall_st) == MODE_WALL_RIGHT
    assert (mem.side, mem.hit_mm) == (MODE_WALL_RIGHT, 3000)
    # not yet clearly closer: stay on the wall, whatever the bearing
    assert enc.update(mem, -300, 3000 - enc.leave_margin_mm + 1, free, free_st) == MODE_WALL_RIGHT
    # closer, but the sensor pointing nearest the goal (-300 mrad: the front one) sees the wall: stay
    assert enc.update(mem, -300, 3000 - enc.leave_margin_mm, wall, wall_st) == MODE_WALL_RIGHT
    side_blocked = list(free), list(free_st)
    side_blocked[0][7], side_blocked[1][7] = 50, V  # front-right: not the goal's direction at -300 mrad
    assert enc.update(mem, -300, 3000 - enc.leave_margin_mm, *side_blocked) == MODE_GO
    mem.mode = MODE_WALL_RIGHT
    assert enc.update(mem, -600, 3000 - enc.leave_margin_mm, *side_blocked) == MODE_WALL_RIGHT  # -600: sensor 7
    assert enc.update(mem, -300, 3000 - enc.leave_margin_mm, free, free_st) == MODE_GO
    # the next hit keeps the side chosen first, although the goal is now to the right
    assert enc.update(mem, -300, 2500, wall, wall_st) == MODE_WALL_RIGHT
    assert mem.hit_mm == 2500
    mem.reset()
    assert (mem.mode, mem.side, mem.hit_mm) == (MODE_GO, 0, 0)
    too_close = list(wall_st)
    too_close[0] = CLOSE
    assert enc.update(mem, -300, 2000, wall, too_close) == MODE_WALL_LEFT


def test_bearing_is_wrapped_before_the_ahead_test():
    enc = MemorySectorEncoder()
    wall, wall_st = _ranges(100)
    mem = BugMemory()
    assert enc.update(mem, 6283 + 100, 1000, wall, wall_st) == MODE_WALL_RIGHT  # +2pi + 0.1 rad: ahead-left
    mem = BugMemory()
    assert enc.update(mem, -6283 - 100, 1000, wall, wall_st) == MODE_WALL_LEFT


def test_state_layout_go_states_then_one_range_block_per_wall_mode():
    enc = MemorySectorEncoder()
    base = enc.base
    r_states = enc.range_states
    assert enc.n_states == 3 * enc.mode_states == 3 * (enc.bearing_sectors + 2) * r_states
    free, free_st = _ranges(1500)
    mem = BugMemory()
    s = enc.encode(mem, 700, 3000, free, free_st)
    assert s == base.encode(700, free, free_st)
    wall, wall_st = _ranges(50)
    s = enc.encode(mem, 100, 3000, wall, wall_st)
    assert mem.mode == MODE_WALL_RIGHT
    assert s == enc.bearing_sectors * r_states + base.encode(100, wall, wall_st) % r_states
    # in a wall mode the bearing does not matter
    assert enc.encode(mem, -2500, 3000, wall, wall_st) == s
    mem.mode = mem.side = MODE_WALL_LEFT
    assert enc.encode(mem, 0, 3000, wall, wall_st) == s + r_states
    # the previous tick's turn is the top digit: turn_right = action 2
    mem.note_action(2)
    assert mem.last_turn == TURN_RIGHT
    assert enc.encode(mem, 0, 3000, wall, wall_st) == s + r_states + 2 * enc.mode_states < enc.n_states
    mem.note_action(0)
    assert enc.encode(mem, 0, 3000, wall, wall_st) == s + r_states


def test_invalid_memory_encoders_refused():
    with pytest.raises(ValueError, match="front sensor"):
        MemorySectorEncoder(sensors=(1, 7))
    with pytest.raises(ValueError, match="block_mm"):
        MemorySectorEncoder(block_mm=0)
    with pytest.raises(ValueError, match="ascending"):
        MemorySectorEncoder(range_edges_mm=(400, 100))


def _table(enc: MemorySectorEncoder, go_action: int, wall_action: int) -> array:
    vals = array("b")
    go_states = enc.bearing_sectors * enc.range_states
    for s in range(enc.n_states):
        a = go_action if s % enc.mode_states < go_states else wall_action
        vals.extend(100 if i == a else 0 for i in range(enc.n_actions))
    return vals


def test_qtab_round_trip_and_damaged_memory_section():
    enc = MemorySectorEncoder(block_mm=350, block_bearing_mrad=600, leave_margin_mm=300)
    data = dump_policy(enc, _table(enc, 0, 1), "int8", 0.01, map_geometry=SECTOR_TRAINING_MAP)
    pol = load_policy(data)
    assert pol.kind == "sector-memory-tick" and pol.encoder == enc and pol.n_states == enc.n_states
    assert pol.header()["encoder"]["leave_margin_mm"] == 300
    # the same bytes declared as a plain sector policy: the section length no longer adds up
    import struct
    import zlib
    bad = bytearray(data[:-4])
    bad[12] = 2  # kind byte (after magic, version, header size, flags): sector
    bad += struct.pack("<I", zlib.crc32(bytes(bad)))
    with pytest.raises(PolicyError, match="sector encoder section is"):
        load_policy(bytes(bad))


def test_controller_runs_the_memory_and_resets_it_per_goal():
    """Go forward in the go mode, turn left in a wall mode: a wall ahead of the
    goal switches the controller's memory to wall following and the robot
    turns; a new goal starts from the go mode again."""
    enc = MemorySectorEncoder()
    pol = load_policy(dump_policy(enc, _table(enc, 0, 1), "int8", 0.01, map_geometry=SECTOR_TRAINING_MAP))
    ctrl = Controller(VehicleConfig(), pol, start_pose_mm=(0, 0, 0))
    rig = Rig(ctrl, Kinematic(0, 0, 0))
    rig.tick()
    assert ctrl.arm() == (True, "")
    assert ctrl.set_goal(3000, 0) == (True, "")
    rig.tick()
    assert ctrl.memory.mode == MODE_GO and rig.last_motor.left_mm_s == rig.last_motor.right_mm_s > 0
    blocked = [200] + [2000] * (N - 1)
    status = [V] + [FAR] * (N - 1)
    rig.tick(ranges_mm=blocked, range_status=status)
    assert ctrl.state == CtrlState.DRIVING and ctrl.memory.mode == MODE_WALL_RIGHT
    assert (rig.last_motor.left_mm_s, rig.last_motor.right_mm_s) == robot_spec.ACTION_WHEEL_SPEEDS_MM_S[1]
    assert ctrl.memory.hit_mm > 2800 and ctrl.memory.last_turn == 1  # turn_left remembered
    assert ctrl.set_goal(0, 3000) == (True, "")
    rig.tick()
    assert ctrl.memory.mode == MODE_GO and ctrl.memory.side == 0 and ctrl.memory.last_turn == 0
