"""The DroneCAN engine's bounded core (issue 43 finding 4): reassembly with a timeout on the robot's
clock and a size cap per data type, rate-limited answers behind the wheel command, node-id collisions."""

from __future__ import annotations

import tracemalloc

import pytest

dronecan = pytest.importorskip("dronecan", reason="the dronecan extra (pip install 'qnav[dronecan]')")

import can  # noqa: E402
from dronecan import transport  # noqa: E402

from firmware_py.dronecan_engine import (  # noqa: E402
    ANSWERS_PER_S,
    COLLISION_HOLD_S,
    MAX_PENDING,
    MAX_TRANSFERS,
    TRANSFER_TIMEOUT_S,
    AnswerQueue,
    DroneCanEngine,
    FrameHeader,
    Reassembler,
    dsdl_max_bytes,
)
from tests.support.dronecan_bus import buffered_bytes, in_progress, waiting  # noqa: E402

ME = 100


def frames_of(payload, source=42, tid=3, **kw) -> list[can.Message]:
    tr = transport.Transfer(payload=payload, source_node_id=source, transfer_id=tid, transfer_priority=24, **kw)
    return [can.Message(arbitration_id=f.message_id, data=bytes(f.bytes), is_extended_id=True) for f in tr.to_frames()]


def log_message(text="x" * 60):
    return dronecan.uavcan.protocol.debug.LogMessage(source="t", text=text)


def continuation(first: can.Message, k: int, end=False) -> can.Message:
    """The k-th frame after `first` (toggle alternating from 1), 7 bytes of payload."""
    tid = first.data[-1] & 0x1F
    tail = tid | (0x20 if k % 2 == 0 else 0) | (0x40 if end else 0)
    return can.Message(arbitration_id=first.arbitration_id, data=bytes(7) + bytes([tail]), is_extended_id=True)


def test_the_header_reads_what_the_library_wrote():
    req = frames_of(dronecan.uavcan.protocol.GetNodeInfo.Request(), source=7, tid=9, dest_node_id=ME,
                    service_not_message=True, request_not_response=True)[0]
    h = FrameHeader.parse(req.arbitration_id, bytes(req.data))
    assert (h.data_type_id, h.service, h.request, h.source, h.dest, h.start, h.end, h.transfer_id) == (
        1, True, True, 7, ME, True, True, 9)
    msg = frames_of(log_message())
    h = FrameHeader.parse(msg[0].arbitration_id, bytes(msg[0].data))
    assert (h.data_type_id, h.service, h.source, h.start, h.end, h.toggle) == (16383, False, 42, True, False, False)
    h = FrameHeader.parse(msg[1].arbitration_id, bytes(msg[1].data))
    assert (h.start, h.end, h.toggle) == (False, False, True)


def test_the_cap_is_the_types_largest_encoding():
    assert dsdl_max_bytes(16383, False, False) == 123  # debug.LogMessage
    assert dsdl_max_bytes(1, True, False) == 377  # GetNodeInfo response
    assert dsdl_max_bytes(1, True, True) == 0
    assert dsdl_max_bytes(65000, False, False) is None


def test_a_real_multi_frame_transfer_still_comes_through():
    eng = DroneCanEngine(ME, "robot", clock=lambda: 0.0)
    frames = frames_of(log_message("hello " * 15))
    assert len(frames) > 10
    out = [eng.take(f, 0.0) for f in frames]
    assert out[:-1] == [None] * (len(frames) - 1)
    assert str(out[-1].payload.text) == "hello " * 15
    assert in_progress(eng.rx) == 0 and eng.bad_transfers == 0


def test_an_endless_transfer_is_dropped_at_its_types_size_and_holds_no_memory():
    eng = DroneCanEngine(ME, "robot", clock=lambda: 0.0)
    first = frames_of(log_message())[0]
    tracemalloc.start()
    try:
        eng.take(first, 0.0)
        base = tracemalloc.get_traced_memory()[0]
        for k in range(100_000):
            assert eng.take(continuation(first, k), 0.0) is None
        held = tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()
    assert held < 100_000, held
    assert in_progress(eng.rx) == 0 and eng.rx.dropped == 1
    assert eng.rx.ignored >= 100_000 - 19  # everything after the cap: a continuation of nothing
    assert eng.take(continuation(first, 100_000, end=True), 0.0) is None  # the end frame: nothing to finish


def test_an_unknown_type_is_dropped_at_its_first_frame():
    first = frames_of(log_message())[0]
    unknown = next(d for d in range(20, 60000) if (d, 1) not in dronecan.DATATYPES)
    arb = (first.arbitration_id & ~(0xFFFF << 8)) | (unknown << 8)
    first = can.Message(arbitration_id=arb, data=first.data, is_extended_id=True)
    eng = DroneCanEngine(ME, "robot", clock=lambda: 0.0)
    eng.take(first, 0.0)
    assert in_progress(eng.rx) == 0 and buffered_bytes(eng.rx) == 0 and eng.rx.dropped == 1


def test_a_transfer_times_out_two_seconds_after_its_first_frame_on_the_callers_clock():
    frames = frames_of(log_message())
    eng = DroneCanEngine(ME, "robot", clock=lambda: 1e9)  # the engine's own clock is not the one used
    eng.take(frames[0], 10.0)
    for f in frames[1:5]:
        eng.take(f, 10.0 + TRANSFER_TIMEOUT_S - 0.1)
    assert in_progress(eng.rx) == 1
    assert eng.take(frames[5], 10.0 + TRANSFER_TIMEOUT_S + 0.1) is None
    assert in_progress(eng.rx) == 0 and eng.rx.timed_out == 1
    # a transfer nobody finishes is swept by the next frame of anything after the timeout
    eng.take(frames[0], 20.0)
    assert in_progress(eng.rx) == 1
    eng.take(frames_of(dronecan.uavcan.protocol.NodeStatus(), source=9)[0], 20.0 + TRANSFER_TIMEOUT_S + 0.5)
    assert in_progress(eng.rx) == 0 and eng.rx.timed_out == 2


def test_wrong_toggle_or_transfer_id_is_ignored_and_the_transfer_still_completes():
    frames = frames_of(log_message())
    eng = DroneCanEngine(ME, "robot", clock=lambda: 0.0)
    eng.take(frames[0], 0.0)
    eng.take(frames[1], 0.0)
    assert eng.take(frames[1], 0.0) is None  # a repeat: wrong toggle
    other = bytes(frames[2].data[:-1]) + bytes([(frames[2].data[-1] & ~0x1F) | 9])
    assert eng.take(can.Message(arbitration_id=frames[2].arbitration_id, data=other, is_extended_id=True), 0.0) is None
    assert eng.rx.ignored == 2
    out = [eng.take(f, 0.0) for f in frames[2:]]
    assert out[-1] is not None and str(out[-1].payload.text) == "x" * 60


def test_at_most_max_transfers_in_progress():
    rx = Reassembler(lambda *_: 100)
    first = frames_of(log_message())[0]
    for src in range(1, MAX_TRANSFERS + 10):
        arb = (first.arbitration_id & ~0x7F) | src
        rx.push(arb, bytes(first.data), 0.0)
    assert in_progress(rx) == MAX_TRANSFERS and rx.dropped == 9


def test_answers_are_one_a_call_bounded_a_second_and_one_per_requester():
    q = AnswerQueue()
    for src in range(1, 60):
        q.add(src, f"req{src}")
    q.add(1, "req1-again")
    assert waiting(q) == MAX_PENDING and q.dropped == 59 - MAX_PENDING
    assert q.due(0.0) == ["req1-again"]
    assert q.due(0.0) == []  # the same tick / no time passed
    got = [a for k in range(1, 21) for a in q.due(k * 0.05)]  # 1 s of 20 Hz ticks
    assert len(got) == ANSWERS_PER_S


def test_node_info_is_answered_from_outgoing_only_at_the_rate():
    eng = DroneCanEngine(ME, "org.qnav.robot", clock=lambda: 0.0)
    for src in range(20, 70):
        for f in frames_of(dronecan.uavcan.protocol.GetNodeInfo.Request(), source=src, tid=src % 32,
                           dest_node_id=ME, service_not_message=True, request_not_response=True):
            eng.take(f, 0.0)
    out = eng.outgoing(0.0)
    assert 0 < len(out) <= 9 and eng.answered_info == 1
    assert all(FrameHeader.parse(m.arbitration_id, bytes(m.data)).dest == 20 for m in out)
    assert eng.outgoing(0.0) == []


def test_another_node_with_our_id_is_a_collision_until_it_is_quiet():
    eng = DroneCanEngine(ME, "robot", clock=lambda: 0.0)
    for f in eng.periodic(0.0) + eng.broadcast(log_message()):  # our own frames, echoed by the bus
        eng.take(f, 0.0)
    assert eng.collision(0.0) == "" and eng.collision_frames == 0
    eng.take(frames_of(dronecan.uavcan.protocol.NodeStatus(uptime_sec=77), source=ME)[0], 5.0)
    text = eng.collision(5.5)
    assert f"node id {ME}" in text and "NodeStatus" in text and len(text) < 150
    assert eng.collision(5.0 + COLLISION_HOLD_S + 0.1) == ""
    assert eng.collision_frames == 1
    # a request sent from our id is one too
    eng.take(frames_of(dronecan.uavcan.protocol.GetNodeInfo.Request(), source=ME, dest_node_id=10,
                       service_not_message=True, request_not_response=True)[0], 9.0)
    assert "GetNodeInfo request" in eng.collision(9.0)


def test_the_backend_sends_the_wheel_command_before_nodestatus_and_answers():
    from pathlib import Path

    from firmware_py.control.io import Heartbeat, MotorCommand, Outputs
    from firmware_py.drives.dronecan import DroneCanBackend
    from firmware_py.profile import load_profile

    prof = load_profile(Path(__file__).resolve().parents[2] / "firmware_py" / "profiles" / "dronecan.toml")
    be = DroneCanBackend(prof, drive=True, sensors=True)
    for src in range(20, 25):
        for f in frames_of(dronecan.uavcan.protocol.GetNodeInfo.Request(), source=src, dest_node_id=ME,
                           service_not_message=True, request_not_response=True):
            be.take(f, 0)
    hb = Heartbeat(state=0, mode=0, armed=True, policy_loaded=True, goal_active=True, errors=0, counter=0)
    out = be.frames(Outputs(motor=MotorCommand(100, 100, 0), heartbeat=hb, drive_enabled=True), 0)
    kinds = [FrameHeader.parse(m.arbitration_id, bytes(m.data)) for m in out]
    assert kinds[0].data_type_id == dronecan.uavcan.equipment.esc.RPMCommand.default_dtid and not kinds[0].service
    assert [k.data_type_id for k in kinds if k.service] and all(k.service for k in kinds[-3:])
    # a collision is the backend's arm_block, for the drive and sensors alike
    be.take(frames_of(dronecan.uavcan.protocol.NodeStatus(), source=ME)[0], 1_000_000)
    blocks = [u.fields["arm_block"] for u in be.check(1_500_000, 500_000) if "arm_block" in u.fields]
    assert len(blocks) == 1 and f"node id {ME}" in blocks[0]
    sensors_only = DroneCanBackend(prof, drive=False, sensors=True)
    sensors_only.take(frames_of(dronecan.uavcan.protocol.NodeStatus(), source=ME)[0], 0)
    assert f"node id {ME}" in sensors_only.check(0, 500_000)[0].fields["arm_block"]


def test_nodestatus_is_due_and_counts_uptime_on_the_robots_clock():
    """In HIL the robot's clock is sim time: NodeStatus goes out once a second of it and its uptime
    counts it, whatever the wall clock (here the engine's own clock stands still)."""
    from pathlib import Path

    from firmware_py.control.io import Heartbeat, Outputs
    from firmware_py.drives.dronecan import DroneCanBackend
    from firmware_py.profile import load_profile

    prof = load_profile(Path(__file__).resolve().parents[2] / "firmware_py" / "profiles" / "dronecan.toml")
    be = DroneCanBackend(prof, drive=True, sensors=True, clock=lambda: 0.0)
    hb = Heartbeat(state=0, mode=0, armed=False, policy_loaded=True, goal_active=False, errors=0, counter=0)
    status_id = dronecan.uavcan.protocol.NodeStatus.default_dtid
    sent = []  # (robot time s, uptime s) of each NodeStatus
    for tick in range(200):  # 10 s at 20 Hz, from t = 100 s
        now_us = 100_000_000 + tick * 50_000
        for m in be.frames(Outputs(motor=None, heartbeat=hb, drive_enabled=False), now_us):
            if FrameHeader.parse(m.arbitration_id, bytes(m.data)).data_type_id == status_id:
                tr = transport.Transfer()
                tr.from_frames([transport.Frame(m.arbitration_id, bytes(m.data))])
                sent.append((now_us / 1e6, tr.payload.uptime_sec))
    assert len(sent) == 10, sent
    assert [round(t - 100) for t, _ in sent] == list(range(10))
    assert [u for _, u in sent] == list(range(10))
