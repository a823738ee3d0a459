"""`--can` resolution and the python-can-remote hub, over real buses."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest

from firmware_py import can_protocol as cp
from firmware_py.canbus import CanSpecError, open_bus, parse_spec
from ground_station.canhub import CanHub
from ground_station.subprocs import free_port


def test_parse_spec_maps_every_documented_form():
    assert parse_spec(None) == {}
    assert parse_spec("") == {}
    assert parse_spec("virtual:qnav") == {"interface": "virtual", "channel": "qnav"}
    assert parse_spec("remote:ws://127.0.0.1:5000/") == {
        "interface": "remote", "channel": "ws://127.0.0.1:5000/"}
    assert parse_spec("socketcan:vcan0") == {"interface": "socketcan", "channel": "vcan0"}
    assert parse_spec("slcan:/dev/ttyACM0@115200") == {
        "interface": "slcan", "channel": "/dev/ttyACM0@115200"}


@pytest.mark.parametrize("spec, words", [
    ("virtual", "expected one of"),
    ("bogus:x", "unknown interface 'bogus'"),
    ("remote:127.0.0.1:5000", "ws:// URL"),
])
def test_bad_specs_give_one_line_errors(spec, words):
    with pytest.raises(CanSpecError, match=words) as info:
        parse_spec(spec)
    assert "\n" not in str(info.value)


def test_unopenable_bus_is_a_one_line_error():
    port = free_port()
    with pytest.raises(CanSpecError, match="cannot open CAN bus") as info:
        open_bus(f"remote:ws://127.0.0.1:{port}/")
    assert "\n" not in str(info.value)


def test_virtual_bus_carries_dbc_frames_between_two_ends():
    a, b = open_bus("virtual:test_can_bus_v"), open_bus("virtual:test_can_bus_v")
    try:
        a.send(cp.motor_command(120, -80, 42))
        name, sig = cp.decode(b.recv(1.0))
        assert name == "MotorCommand" and sig["Cmd_Counter"] == 42
        assert a.recv(0.05) is None  # no echo of own frames
    finally:
        a.shutdown()
        b.shutdown()


def test_default_config_comes_from_python_can_environment(monkeypatch):
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "test_can_bus_env")
    a, b = open_bus(None), open_bus("virtual:test_can_bus_env")
    try:
        a.send(cp.sim_tick(1, 50_000))
        assert cp.decode(b.recv(1.0))[0] == "SimTick"
    finally:
        a.shutdown()
        b.shutdown()


def test_hub_carries_frames_across_processes_and_stops():
    code = ("import sys\nfrom firmware_py.canbus import open_bus\n"
            "from firmware_py import can_protocol as cp\n"
            "bus = open_bus(sys.argv[1])\n"
            "msg = bus.recv(10)\n"
            "_, sig = cp.decode(msg)\n"
            "bus.send(cp.motor_command(1, 2, sig['Tick_Counter']))\n"
            "bus.shutdown()\n")
    with CanHub("test_hub") as hub:
        assert hub.spec.startswith("remote:ws://127.0.0.1:")
        bus = open_bus(hub.spec)
        child = subprocess.Popen([sys.executable, "-c", code, hub.spec])
        try:
            reply = None
            for _ in range(100):  # the child may connect after our first tick: resend
                bus.send(cp.sim_tick(77, 3_850_000))
                reply = bus.recv(0.1)
                if reply is not None:
                    break
            assert reply is not None
            assert cp.decode(reply) == ("MotorCommand", {
                "Cmd_LeftSpeed": 1, "Cmd_RightSpeed": 2, "Cmd_Counter": 77})
            assert child.wait(20) == 0
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
            bus.shutdown()
        port = hub.port
    assert not hub.running
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=0.5).close()

