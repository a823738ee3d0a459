"""The robot's CAN protocol, read from `qnav.dbc` (the single source of truth).

This module owns encoding and decoding of every frame on the robot's bus. The DBC is loaded once
from the package data; frame ids, node ids and counter widths below are derived from it, never
retyped. Encoding is strict: a missing signal or a value outside its DBC range raises
`ProtocolError` instead of being silently truncated on the wire.

Layout: 11-bit id = node_id << 5 | cmd_id (the shape of ODrive's CANSimple), 8-byte little-endian
frames, on nodes 32..37 and 63: an ODrive at any node id 0..31 (ids up to 0x3FF) and every DroneCAN
node (29-bit ids) share the bus without a collision. See docs/can-protocol.md for rates, senders and
the lockstep handshake.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from importlib import resources

import can
import cantools
from cantools.database.can import Database
from cantools.database.can import Message as DbcMessage

from firmware_py import robot_spec

CMD_BITS = 5  # as ODrive CANSimple: the low 5 bits of the id are the command
CMD_MASK = (1 << CMD_BITS) - 1


class ProtocolError(ValueError):
    """A frame that cannot be encoded or decoded; the text is one line."""


def _load() -> Database:
    text = resources.files("firmware_py").joinpath("qnav.dbc").read_text(encoding="utf-8")
    db = cantools.database.load_string(text, database_format="dbc", strict=True)
    assert isinstance(db, Database)  # a "dbc" always loads as a CAN database
    return db


DB: Database = _load()
_BY_NAME: dict[str, DbcMessage] = {m.name: m for m in DB.messages}
_BY_ID: dict[int, DbcMessage] = {m.frame_id: m for m in DB.messages}


def split_id(frame_id: int) -> tuple[int, int]:
    """(node_id, cmd_id) of an 11-bit frame id."""
    return frame_id >> CMD_BITS, frame_id & CMD_MASK


def _id(name: str) -> int:
    return _BY_NAME[name].frame_id


# --- frame ids (from the DBC) ----------------------------------------------
ESTOP_ID = _id("EStop")
CONTROLLER_HEARTBEAT_ID = _id("ControllerHeartbeat")
MOTOR_STATUS_ID = _id("MotorStatus")
ENCODER_COUNTS_ID = _id("EncoderCounts")
MOTOR_COMMAND_ID = _id("MotorCommand")
RANGE_SECTORS_IDS: tuple[int, ...] = (_id("RangeSectors0"), _id("RangeSectors1"))
BUMPER_ID = _id("Bumper")
SIM_TICK_ID = _id("SimTick")
FRAME_IDS: dict[str, int] = {m.name: m.frame_id for m in DB.messages}

# --- node ids (the high 6 bits of each node's frames) -----------------------
NODE_BROADCAST = split_id(ESTOP_ID)[0]
NODE_CONTROLLER = split_id(CONTROLLER_HEARTBEAT_ID)[0]
NODE_MOTOR_DRIVER = split_id(MOTOR_STATUS_ID)[0]
NODE_RANGE_BOARD = split_id(RANGE_SECTORS_IDS[0])[0]
NODE_BUMPER_BOARD = split_id(BUMPER_ID)[0]
NODE_SIM = split_id(SIM_TICK_ID)[0]

# --- counters ----------------------------------------------------------------
TICK_MODULUS = 1 << _BY_NAME["SimTick"].get_signal_by_name("Tick_Counter").length
COMMAND_COUNTER_MODULUS = 1 << _BY_NAME["MotorCommand"].get_signal_by_name("Cmd_Counter").length
SENSORS_PER_RANGE_FRAME = robot_spec.SENSOR_COUNT // len(RANGE_SECTORS_IDS)
ENCODER_BITS = _BY_NAME["EncoderCounts"].get_signal_by_name("Enc_Left").length  # counts wrap modulo 2^bits
# Rolling counter of each sensor frame (+1 per new sample): a sender stuck on
# one frame is told from a live one by a counter that stops advancing.
SENSOR_COUNTER_SIGNALS: dict[str, str] = {
    "RangeSectors0": "Rng0_Counter", "RangeSectors1": "Rng1_Counter",
    "EncoderCounts": "Enc_Counter", "Bumper": "Bump_Counter", "MotorStatus": "Mot_Counter",
}
SENSOR_COUNTER_MODULUS = 1 << _BY_NAME["EncoderCounts"].get_signal_by_name("Enc_Counter").length
assert all(1 << _BY_NAME[f].get_signal_by_name(c).length == SENSOR_COUNTER_MODULUS
           for f, c in SENSOR_COUNTER_SIGNALS.items())

# Motor driver state (Mot_State) and error bits (Mot_Errors), as in the DBC.
_MOT_STATE_CHOICES = _BY_NAME["MotorStatus"].get_signal_by_name("Mot_State").choices
assert _MOT_STATE_CHOICES is not None, "qnav.dbc: Mot_State has no value table"
_MOT_STATES = {str(name): int(value) for value, name in _MOT_STATE_CHOICES.items()}
MOTOR_IDLE = _MOT_STATES["IDLE"]
MOTOR_RUNNING = _MOT_STATES["RUNNING"]
MOTOR_WATCHDOG_STOP = _MOT_STATES["WATCHDOG_STOP"]
MOTOR_ESTOP = _MOT_STATES["ESTOP"]
MOTOR_STATE_NAMES = {value: name for name, value in _MOT_STATES.items()}
MOTOR_ERR_BAD_COMMAND = 1
MOTOR_ERR_STALL_LEFT = 2
MOTOR_ERR_STALL_RIGHT = 4


def encode(name: str, signals: Mapping[str, int], timestamp: float = 0.0) -> can.Message:
    """Encode frame `name` strictly (all signals present, each inside its range)."""
    try:
        spec = _BY_NAME[name]
    except KeyError:
        raise ProtocolError(f"unknown CAN frame {name!r}") from None
    try:
        data = spec.encode(dict(signals), scaling=True, padding=False, strict=True)
    except (cantools.database.EncodeError, KeyError, ValueError) as exc:
        raise ProtocolError(f"cannot encode {name}: {exc}") from None
    return can.Message(arbitration_id=spec.frame_id, data=data, is_extended_id=False,
                       dlc=spec.length, timestamp=timestamp)


def decode(msg: can.Message) -> tuple[str, dict[str, int]]:
    """(frame name, signals as ints) of a frame on our bus; ProtocolError otherwise."""
    if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
        raise ProtocolError(f"not a qnav data frame: id 0x{msg.arbitration_id:x}")
    spec = _BY_ID.get(msg.arbitration_id)
    if spec is None:
        raise ProtocolError(f"unknown CAN id 0x{msg.arbitration_id:03x}")
    if len(msg.data) != spec.length:
        raise ProtocolError(f"{spec.name}: {len(msg.data)} data bytes, expected {spec.length}")
    try:
        values = spec.decode_simple(bytes(msg.data), decode_choices=False, scaling=True)
    except cantools.database.DecodeError as exc:
        raise ProtocolError(f"cannot decode {spec.name}: {exc}") from None
    # cantools types a value as int | float | str | NamedSignalValue whatever
    # decode_choices says; with decode_choices=False it is a number.
    return spec.name, {k: int(v) for k, v in values.items()}  # type: ignore[arg-type]


def frame_name(frame_id: int) -> str | None:
    spec = _BY_ID.get(frame_id)
    return spec.name if spec is not None else None


# --- typed constructors for the frames of every control tick ------------------

def motor_command(left_mm_s: int, right_mm_s: int, counter: int) -> can.Message:
    """MotorCommand; `counter` is taken modulo the counter width."""
    return encode("MotorCommand", {"Cmd_LeftSpeed": left_mm_s, "Cmd_RightSpeed": right_mm_s,
                                   "Cmd_Counter": counter % COMMAND_COUNTER_MODULUS})


def sim_tick(tick: int, sim_time_us: int) -> can.Message:
    """SimTick for control tick `tick` (taken modulo the counter width)."""
    return encode("SimTick", {"Tick_Counter": tick % TICK_MODULUS, "Tick_SimTimeUs": sim_time_us})


def wrap_counts(ticks: int) -> int:
    """A cumulative encoder count as the frame carries it (ENCODER_BITS two's complement)."""
    half = 1 << (ENCODER_BITS - 1)
    return (ticks + half) % (1 << ENCODER_BITS) - half


def encoder_counts(left: int, right: int, counter: int) -> can.Message:
    """EncoderCounts from cumulative counts (wrapped to the frame's width) and the sample counter."""
    return encode("EncoderCounts", {"Enc_Left": wrap_counts(left), "Enc_Right": wrap_counts(right),
                                    "Enc_Counter": counter % SENSOR_COUNTER_MODULUS})


def range_frames(readings: Sequence[tuple[int, int]], counter: int = 0) -> list[can.Message]:
    """RangeSectors frames from (mm, status) per sensor, in robot_spec.SENSOR_ANGLES_MRAD order,
    carrying the sample `counter` (taken modulo the counter width)."""
    if len(readings) != robot_spec.SENSOR_COUNT:
        raise ProtocolError(f"expected {robot_spec.SENSOR_COUNT} range readings, got {len(readings)}")
    frames = []
    for f in range(len(RANGE_SECTORS_IDS)):
        signals = {f"Rng{f}_Counter": counter % SENSOR_COUNTER_MODULUS}
        for i in range(f * SENSORS_PER_RANGE_FRAME, (f + 1) * SENSORS_PER_RANGE_FRAME):
            mm, status = readings[i]
            signals[f"Range{i}"] = mm
            signals[f"Range{i}Status"] = status
        frames.append(encode(f"RangeSectors{f}", signals))
    return frames


def ranges_from(name: str, signals: Mapping[str, int]) -> dict[int, tuple[int, int]]:
    """{sensor index: (mm, status)} from a decoded RangeSectors frame."""
    first = int(name.removeprefix("RangeSectors")) * SENSORS_PER_RANGE_FRAME
    return {i: (signals[f"Range{i}"], signals[f"Range{i}Status"])
            for i in range(first, first + SENSORS_PER_RANGE_FRAME)}
