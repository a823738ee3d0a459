"""The `sector-unmapped` kind on the robot: its `.qtab` round trip and damaged
sections refused, and the controller running it with its pose and the
policy's map (detour on an unmapped reading, none on a map wall, the go rows
without a map, the memory reset per goal)."""

from __future__ import annotations

import struct
import zlib
from array import array

import pytest

from firmware_py import robot_spec
from firmware_py.control.controller import Controller
from firmware_py.policy import PolicyError, dump_policy, load_policy
from firmware_py.unmapped import UnmappedSectorEncoder
from firmware_py.vehicle import VehicleConfig
from tests.support.controller_rig import SECTOR_TRAINING_MAP, Kinematic, Rig

V, FAR = robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_FAR
N = robot_spec.SENSOR_COUNT
ENC = UnmappedSectorEncoder(margin_mm=120, block_mm=350, block_bearing_mrad=700, leave_margin_mm=50, leave=0,
                            clear_mm=450, switch_ticks=77, rejoin=1)
OPEN = ["." * 10] * 10
WALL = ["." * 3 + "@" + "." * 6] * 10  # column 3: x 1500..2000 mm


def _table(go_action: int, detour_action: int) -> array:
    vals = array("b")
    for s in range(ENC.n_states):
        a = go_action if s < ENC.n_go else detour_action
        vals.extend(100 if i == a else 0 for i in range(ENC.n_actions))
    return vals


def _policy(rows: list[str] | None) -> bytes:
    meta = {"map_grid": rows} if rows is not None else {}
    return dump_policy(ENC, _table(0, 1), "int8", 0.01, map_geometry=SECTOR_TRAINING_MAP, metadata=meta)


def test_qtab_round_trip():
    pol = load_policy(_policy(OPEN))
    assert pol.kind == "sector-unmapped" and pol.encoder == ENC and pol.n_states == ENC.n_states
    assert pol.map_grid is not None and pol.map_grid.width == 10
    assert pol.header()["encoder"]["detour_sensors"] == [0, 1, 2, 6, 7] and pol.header()["encoder"]["leave"] == 0
    assert pol.header()["encoder"]["switch_ticks"] == 77 and pol.header()["encoder"]["clear_mm"] == 450
    assert pol.header()["encoder"]["rejoin"] == 1


def _resealed(data: bytes, at: int, value: int) -> bytes:
    bad = bytearray(data[:-4])
    bad[at] = value
    return bytes(bad) + struct.pack("<I", zlib.crc32(bytes(bad)))


def test_damaged_detour_sections_are_refused():
    data = _policy(None)
    at = data.index(bytes([5, 0, 1, 2, 6, 7]))  # the detour sensor count, then the sensors
    assert data.count(bytes([5, 0, 1, 2, 6, 7])) == 1
    with pytest.raises(PolicyError, match="sector encoder section is"):
        load_policy(_resealed(data, at, 9))
    with pytest.raises(PolicyError, match="sector-unmapped encoder: detour sensor"):
        load_policy(_resealed(data, at + 1, 8))  # sensor index 8 on an 8-sensor robot
    with pytest.raises(PolicyError, match="sector-unmapped encoder: detour sensors must be distinct"):
        load_policy(_resealed(data, at + 2, 0))
    with pytest.raises(PolicyError, match="sector-unmapped encoder: leave_margin_mm must be >= 0 and leave 0 or 1"):
        load_policy(_resealed(data, at + 1 + 5 + 8, 2))  # leave = 2
    with pytest.raises(PolicyError, match="sector encoder section is"):
        load_policy(_resealed(data, 12, 2))  # declared a plain sector policy


def _drive(rows: list[str] | None, front_mm: int) -> tuple[Controller, Rig]:
    ctrl = Controller(VehicleConfig(), load_policy(_policy(rows)), start_pose_mm=(1000, 2250, 0), localise=False)
    rig = Rig(ctrl, Kinematic(1000, 2250, 0))
    rig.tick()
    assert ctrl.arm() == (True, "")
    assert ctrl.set_goal(4250, 2250) == (True, "")
    ranges = [front_mm] + [2000] * (N - 1)
    status = [V] + [FAR] * (N - 1)
    rig.tick(ranges_mm=ranges, range_status=status)
    return ctrl, rig


def test_controller_detours_round_an_unmapped_reading_only():
    # front sensor at x 1150; a reading of 350 ends at x 1500, the wall column's face
    ctrl, rig = _drive(OPEN, 300)  # open map: nothing there -> unmapped, detour rows (turn left)
    assert ctrl.detour.detour and ctrl._state_index >= ENC.n_go
    assert (rig.last_motor.left_mm_s, rig.last_motor.right_mm_s) == robot_spec.ACTION_WHEEL_SPEEDS_MM_S[1]
    assert ctrl.detour.last_turn == 1
    ctrl, rig = _drive(WALL, 300)  # the map's wall explains it: go rows (forward)
    assert not ctrl.detour.detour and ctrl._state_index < ENC.n_go
    assert rig.last_motor.left_mm_s == rig.last_motor.right_mm_s > 0
    ctrl, rig = _drive(None, 300)  # no map on the robot: the go rows, whatever it reads
    assert not ctrl.detour.detour and rig.last_motor.left_mm_s == rig.last_motor.right_mm_s > 0


def test_controller_resets_the_detour_per_goal():
    ctrl, rig = _drive(OPEN, 300)
    assert ctrl.detour.detour and ctrl.detour.side != 0
    assert ctrl.set_goal(1000, 4250) == (True, "")
    rig.tick()
    assert not ctrl.detour.detour and ctrl.detour.side == 0
