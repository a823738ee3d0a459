"""The robot's transmit budget on a serial link (firmware_py/mavlink/tx_budget.py): the core on
an injected clock, then the real node shell on a pseudo-terminal at 57600 baud with every
telemetry stream asked for at 50 Hz: what comes out stays within the line's byte rate, the
heartbeat keeps its 1 Hz and a command is still answered."""

from __future__ import annotations

import os
import select
import time
import tty

import pytest

from firmware_py.clock import SimClock
from firmware_py.mavlink.dialect import mavlink2 as m
from firmware_py.mavlink.node import open_node
from firmware_py.mavlink.tx_budget import TELEMETRY_SHARE, TxBudget, frame_len
from tests.support.mav_vehicle import TestVehicle
from tests.support.sim_time import advance_us


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def test_streams_thin_out_to_the_rate_and_replies_always_go():
    clk = _Clock()
    b = TxBudget(1000.0, burst_s=0.5, clock=clk)  # 1000 B/s, 500 B saved up at most
    sent = 0
    for _ in range(2000):  # 20 s of 100-byte stream frames asked for every 10 ms (10 kB/s)
        clk.t += 0.01
        if b.allow(100, stream=True):
            sent += 100
    assert 20 * 1000 - 500 <= sent <= 20 * 1000 + 500
    assert b.dropped > 1500
    assert b.allow(400, stream=False) and b.allow(400, stream=False)  # replies go, into debt
    assert not b.allow(10, stream=True)  # streams wait until the debt is paid
    clk.t += 1.0
    assert b.allow(10, stream=True)
    with pytest.raises(ValueError):
        TxBudget(0.0)


def test_frame_len_bounds_the_wire_length():
    mav = m.MAVLink(None, 1, 1)
    for msg in (mav.heartbeat_encode(1, 2, 3, 4, 5),
                mav.obstacle_distance_encode(0, 0, [65535] * 72, 5, 2, 200, 5.0, 0.0, 12),
                mav.statustext_encode(4, b"no progress for 10 s")):
        assert len(msg.pack(mav)) <= frame_len(msg, signed=False) <= len(msg.pack(mav)) + 255
    assert frame_len(mav.heartbeat_encode(1, 2, 3, 4, 5), signed=True) == 12 + 2 + 9 + 13


def test_node_on_a_57600_baud_line_keeps_within_it_and_still_answers(tmp_path):
    gcs_fd, robot_fd = os.openpty()
    tty.setraw(gcs_fd)
    tty.setraw(robot_fd)
    robot_dev = os.ttyname(robot_fd)
    clock = SimClock(1_000_000)
    shell = open_node(TestVehicle(), tmp_path, robot_dev, clock.now_us(), baud=57600, ftp=False)
    try:
        assert shell.tx_budget is not None
        gcs = m.MAVLink(None, 255, 190)
        for msg_id in (m.MAVLINK_MSG_ID_ODOMETRY, m.MAVLINK_MSG_ID_LOCAL_POSITION_NED_COV,
                       m.MAVLINK_MSG_ID_OBSTACLE_DISTANCE, m.MAVLINK_MSG_ID_ATTITUDE,
                       m.MAVLINK_MSG_ID_LOCAL_POSITION_NED, m.MAVLINK_MSG_ID_NAMED_VALUE_INT):
            os.write(gcs_fd, gcs.command_long_encode(1, 1, m.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                     msg_id, 20_000, 0, 0, 0, 0, 0).pack(gcs))
        got = bytearray()
        t0 = time.monotonic()
        asked = False
        while time.monotonic() - t0 < 3.0:  # the robot clock paced at wall time, one poll per 50 ms period
            advance_us(clock, 50_000)
            shell.poll(clock.now_us())
            if not asked and time.monotonic() - t0 > 2.0:
                os.write(gcs_fd, gcs.command_long_encode(1, 1, m.MAV_CMD_REQUEST_MESSAGE, 0,
                                                         m.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0).pack(gcs))
                asked = True
            while select.select([gcs_fd], [], [], 0)[0]:
                got += os.read(gcs_fd, 65536)
            time.sleep(max(0.0, t0 + (clock.now_us() - 1_000_000) / 1e6 - time.monotonic()))
        took = time.monotonic() - t0
        while select.select([gcs_fd], [], [], 0.2)[0]:
            got += os.read(gcs_fd, 65536)
    finally:
        shell.close()
        os.close(gcs_fd)
        os.close(robot_fd)
    parser = m.MAVLink(None, 255, 190)
    msgs = [x for x in parser.parse_buffer(bytes(got)) or [] if x.get_type() != "BAD_DATA"]
    kinds = [x.get_type() for x in msgs]
    rate = 57600 / 10 * TELEMETRY_SHARE
    # six streams at 50 Hz want ~40 kB/s; the line's share is 4608 B/s (+ the burst saved up at the start)
    assert len(got) <= rate * took + rate * 0.5 + 1000, (len(got), took)
    assert len(got) >= 0.5 * rate * took  # and the share is used, not wasted
    assert shell.tx_budget.dropped > 100
    assert kinds.count("HEARTBEAT") >= 2
    assert "AUTOPILOT_VERSION" in kinds  # a reply still goes out on a saturated line
    acks = [x for x in msgs if x.get_type() == "COMMAND_ACK" and x.command == m.MAV_CMD_SET_MESSAGE_INTERVAL]
    assert len(acks) == 6 and all(a.result == m.MAV_RESULT_ACCEPTED for a in acks)
