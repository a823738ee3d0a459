"""The DBC and its codec: every frame round-trips, strictness, tooling (dump, C)."""

from __future__ import annotations

import random
import shutil
import subprocess
import sys
from pathlib import Path

import can
import pytest

from firmware_py import can_protocol as cp
from firmware_py import robot_spec, vehicle

DBC = Path(cp.__file__).with_name("qnav.dbc")


def _random_signals(msg, rng: random.Random) -> dict[str, int]:
    return {s.name: rng.randint(int(s.minimum), int(s.maximum)) for s in msg.signals}


def test_every_frame_round_trips_through_the_dbc_at_limits_and_random_values():
    rng = random.Random(7)
    for spec in cp.DB.messages:
        cases = [{s.name: int(s.minimum) for s in spec.signals},
                 {s.name: int(s.maximum) for s in spec.signals}]
        cases += [_random_signals(spec, rng) for _ in range(200)]
        for signals in cases:
            msg = cp.encode(spec.name, signals)
            assert isinstance(msg, can.Message)
            assert msg.arbitration_id == spec.frame_id and not msg.is_extended_id
            assert len(msg.data) == 8
            name, decoded = cp.decode(msg)
            assert name == spec.name
            assert decoded == signals


def test_every_frame_has_the_odrive_shape_and_the_required_set_exists():
    names = set(cp.FRAME_IDS)
    assert {"EStop", "ControllerHeartbeat", "MotorStatus", "EncoderCounts", "MotorCommand",
            "RangeSectors0", "RangeSectors1", "Bumper", "SimTick"} <= names
    ids = [m.frame_id for m in cp.DB.messages]
    assert len(set(ids)) == len(ids)
    for m in cp.DB.messages:
        assert m.length == 8 and not m.is_extended_frame and m.frame_id < 2048
        node, cmd = cp.split_id(m.frame_id)
        assert m.frame_id == node << 5 | cmd and node < 64 and cmd < 32
        assert all(s.byte_order == "little_endian" for s in m.signals)
    assert min(ids) == cp.ESTOP_ID and max(ids) == cp.SIM_TICK_ID
    assert cp.split_id(cp.MOTOR_COMMAND_ID) == (cp.NODE_MOTOR_DRIVER, 0x0D)
    assert cp.split_id(cp.ENCODER_COUNTS_ID) == (cp.NODE_MOTOR_DRIVER, 0x0A)


def test_qnav_ids_stay_clear_of_odrive_nodes_and_dronecan():
    """An ODrive at node n uses ids n << 5 | cmd (cmd 0..31): qnav's frames sit above every id of ODrive
    nodes 0..31, and none is extended (every DroneCAN frame is)."""
    odrive_ids = {node << 5 | cmd for node in range(32) for cmd in range(32)}
    assert not odrive_ids & {m.frame_id for m in cp.DB.messages}
    assert min(m.frame_id for m in cp.DB.messages) > max(odrive_ids)
    assert not any(m.is_extended_frame for m in cp.DB.messages)


def test_range_status_values_are_dronecans_reading_types():
    # uavcan.equipment.range_sensor.Measurement: READING_TYPE_UNDEFINED 0, VALID_RANGE 1, TOO_CLOSE 2, TOO_FAR 3
    assert (robot_spec.RANGE_INVALID, robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_CLOSE,
            robot_spec.RANGE_TOO_FAR) == (0, 1, 2, 3)
    choices = cp.DB.get_message_by_name("RangeSectors0").get_signal_by_name("Range0Status").choices
    assert choices is not None and {str(v): k for k, v in choices.items()}["VALID"] == robot_spec.RANGE_VALID
    name, sig = cp.decode(cp.range_frames([(0, 0)] * robot_spec.SENSOR_COUNT)[0])
    assert sig["Range0Status"] == robot_spec.RANGE_INVALID  # an all-zero slot is no reading


def test_dbc_agrees_with_the_robot_contract_and_vehicle_enums():
    cmd = cp.DB.get_message_by_name("MotorCommand")
    for s in cmd.signals[:2]:
        assert (s.minimum, s.maximum) == (-robot_spec.MAX_WHEEL_SPEED_MM_S, robot_spec.MAX_WHEEL_SPEED_MM_S)
    hb = cp.DB.get_message_by_name("ControllerHeartbeat")
    states = {str(v): k for k, v in hb.get_signal_by_name("Ctrl_State").choices.items()}
    assert states == {s.name: s.value for s in vehicle.CtrlState}
    modes = {str(v): k for k, v in hb.get_signal_by_name("Ctrl_Mode").choices.items()}
    assert modes == {m.name: m.value for m in vehicle.Mode}
    status = cp.DB.get_message_by_name("RangeSectors0").get_signal_by_name("Range0Status").choices
    assert {str(v): k for k, v in status.items()} == {
        "VALID": robot_spec.RANGE_VALID, "TOO_CLOSE": robot_spec.RANGE_TOO_CLOSE,
        "TOO_FAR": robot_spec.RANGE_TOO_FAR, "INVALID": robot_spec.RANGE_INVALID}
    rng = cp.DB.get_message_by_name("RangeSectors0").get_signal_by_name("Range0")
    assert rng.maximum >= robot_spec.RANGE_MAX_MM
    assert len(cp.RANGE_SECTORS_IDS) * cp.SENSORS_PER_RANGE_FRAME == robot_spec.SENSOR_COUNT
    assert cp.TICK_MODULUS == cp.COMMAND_COUNTER_MODULUS  # a command can echo any tick


def test_strict_encoding_rejects_out_of_range_and_missing_signals():
    with pytest.raises(cp.ProtocolError, match="MotorCommand"):
        cp.motor_command(robot_spec.MAX_WHEEL_SPEED_MM_S + 1, 0, 0)
    with pytest.raises(cp.ProtocolError, match="Bump_Pressed"):
        cp.encode("Bumper", {})
    with pytest.raises(cp.ProtocolError, match="unknown CAN frame"):
        cp.encode("NoSuchFrame", {})
    with pytest.raises(cp.ProtocolError):
        cp.range_frames([(100, 0)] * (robot_spec.SENSOR_COUNT - 1))


def test_decode_rejects_foreign_short_and_extended_frames():
    with pytest.raises(cp.ProtocolError, match="unknown CAN id 0x3ff"):
        cp.decode(can.Message(arbitration_id=0x3FF, data=bytes(8), is_extended_id=False))
    with pytest.raises(cp.ProtocolError, match="4 data bytes"):
        cp.decode(can.Message(arbitration_id=cp.SIM_TICK_ID, data=bytes(4), is_extended_id=False))
    with pytest.raises(cp.ProtocolError, match="not a qnav data frame"):
        cp.decode(can.Message(arbitration_id=cp.SIM_TICK_ID, data=bytes(8), is_extended_id=True))


def test_typed_helpers_wrap_counters_and_split_ranges():
    _, sig = cp.decode(cp.sim_tick(cp.TICK_MODULUS + 5, 123_456_789_012))
    assert sig == {"Tick_Counter": 5, "Tick_SimTimeUs": 123_456_789_012}
    _, sig = cp.decode(cp.motor_command(-600, 250, 2 * cp.COMMAND_COUNTER_MODULUS + 9))
    assert sig == {"Cmd_LeftSpeed": -600, "Cmd_RightSpeed": 250, "Cmd_Counter": 9}
    readings = [(100 + i, i % 4) for i in range(robot_spec.SENSOR_COUNT)]
    got = {}
    for frame in cp.range_frames(readings):
        got.update(cp.ranges_from(*cp.decode(frame)))
    assert [got[i] for i in range(robot_spec.SENSOR_COUNT)] == readings


def test_cantools_dump_reads_the_dbc():
    out = subprocess.run([sys.executable, "-m", "cantools", "dump", str(DBC)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    for name in cp.FRAME_IDS:
        assert f"Name:           {name}" in out.stdout


def test_generated_c_source_compiles(tmp_path):
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler on PATH (cc/gcc); the CI image has one")
    out = subprocess.run([sys.executable, "-m", "cantools", "generate_c_source", str(DBC),
                          "-o", str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    c_file = tmp_path / "qnav.c"
    assert (tmp_path / "qnav.h").exists() and c_file.exists()
    header = (tmp_path / "qnav.h").read_text()
    assert "QNAV_MOTOR_COMMAND_FRAME_ID (0x44du)" in header
    comp = subprocess.run([cc, "-std=c99", "-Wall", "-Werror", "-c", str(c_file), "-o",
                           str(tmp_path / "qnav.o")], capture_output=True, text=True, timeout=60)
    assert comp.returncode == 0, comp.stderr
    assert (tmp_path / "qnav.o").stat().st_size > 0
