"""Two ODrive axes on a CAN bus, played from ODrive's published CANSimple protocol alone.

A stand-in for a robot builder's ODrive board, written without qnav's drive
backend or its sim: each axis (node id N) answers to `N << 5 | cmd` as ODrive
documents it -- Set_Axis_State 0x07 (IDLE 1, CLOSED_LOOP_CONTROL 8),
Set_Controller_Mode 0x0B, Set_Input_Vel 0x0D (float32 turns/s), Clear_Errors
0x18, Estop 0x02 -- and sends Heartbeat 0x01 (Axis_Error u32, Axis_State u8)
every 100 ms and Get_Encoder_Estimates 0x09 (float32 turns, turns/s) every
10 ms, with a 0.5 s velocity watchdog. The wheels move a differential-drive
robot in an empty field (unicycle model, wall clock); the robot's range and
bumper boards are played on qnav's own frames from qnav.dbc (all ranges too
far), so `qnav-robot --profile firmware_py/profiles/odrive.toml` on the same
bus can drive it to a goal.

    python tools/odrive_pair.py --can remote:ws://127.0.0.1:PORT/ --duration 30 --json end.json

Prints (and writes with --json) the final pose and what each axis received.
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import sys
import time
from pathlib import Path

import can
import cantools

DBC = Path(__file__).resolve().parents[1] / "firmware_py" / "qnav.dbc"
IDLE, CLOSED_LOOP = 1, 8
VELOCITY_CONTROL = 2
WATCHDOG_S = 0.5


class Axis:
    def __init__(self, node: int, sign: int) -> None:
        self.node, self.sign = node, sign
        self.state, self.error, self.control_mode = IDLE, 0, 0
        self.vel_cmd = 0.0
        self.last_cmd_s = 0.0
        self.pos = 0.0
        self.received: dict[str, int] = {}

    def on_frame(self, cmd: int, data: bytes, now: float) -> None:
        name = {0x02: "Estop", 0x07: "Set_Axis_State", 0x0B: "Set_Controller_Mode", 0x0D: "Set_Input_Vel",
                0x18: "Clear_Errors"}.get(cmd)
        if name is None:
            return
        self.received[name] = self.received.get(name, 0) + 1
        if cmd == 0x07 and len(data) >= 4:
            want = struct.unpack_from("<I", data)[0]
            if want == CLOSED_LOOP and not self.error:
                self.state, self.last_cmd_s = CLOSED_LOOP, now
            elif want == IDLE:
                self.state, self.vel_cmd = IDLE, 0.0
        elif cmd == 0x0B and len(data) >= 8:
            self.control_mode = struct.unpack_from("<I", data)[0]
        elif cmd == 0x0D and len(data) >= 8:
            self.vel_cmd, self.last_cmd_s = struct.unpack_from("<f", data)[0], now
        elif cmd == 0x18:
            self.error = 0
        elif cmd == 0x02:
            self.error, self.state, self.vel_cmd = 0x4000, IDLE, 0.0

    def velocity(self, now: float) -> float:
        """turns/s the motor turns at now (the watchdog trips after WATCHDOG_S without Set_Input_Vel)."""
        if self.state == CLOSED_LOOP and now - self.last_cmd_s > WATCHDOG_S:
            self.error, self.state, self.vel_cmd = 0x800, IDLE, 0.0
        return self.vel_cmd if self.state == CLOSED_LOOP and self.control_mode == VELOCITY_CONTROL else 0.0


def open_bus(spec: str) -> can.BusABC:
    interface, _, channel = spec.partition(":")
    return can.Bus(interface=interface, channel=channel)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--can", required=True, help="python-can INTERFACE:CHANNEL (virtual:x, remote:ws://..., socketcan:can0)")
    p.add_argument("--left-node", type=int, default=0)
    p.add_argument("--right-node", type=int, default=1)
    p.add_argument("--right-mount", type=int, default=-1, help="+1/-1: the right motor faces the other way")
    p.add_argument("--wheel-radius-mm", type=float, default=40.0)
    p.add_argument("--wheel-base-mm", type=float, default=260.0)
    p.add_argument("--start", default="0,0,0", help="x_m,y_m,heading_deg")
    p.add_argument("--duration", type=float, default=30.0, help="wall seconds")
    p.add_argument("--json", help="write the end state here")
    args = p.parse_args(argv)
    db = cantools.database.load_file(str(DBC))
    ranges = [db.get_message_by_name(f"RangeSectors{i}") for i in (0, 1)]
    bumper = db.get_message_by_name("Bumper")
    too_far = {str(v): k for k, v in ranges[0].get_signal_by_name("Range0Status").choices.items()}["TOO_FAR"]
    axes = {args.left_node: Axis(args.left_node, 1), args.right_node: Axis(args.right_node, args.right_mount)}
    left, right = axes[args.left_node], axes[args.right_node]
    x, y, th = (float(v) for v in args.start.split(","))
    th = math.radians(th)
    circ_m = 2 * math.pi * args.wheel_radius_mm / 1000
    bus = open_bus(args.can)
    t0 = last = time.monotonic()
    tick = 0
    try:
        while (now := time.monotonic()) - t0 < args.duration:
            msg = bus.recv(timeout=0.002)
            while msg is not None:
                axis = axes.get(msg.arbitration_id >> 5)
                if axis is not None and not msg.is_extended_id:
                    axis.on_frame(msg.arbitration_id & 0x1F, bytes(msg.data), now)
                msg = bus.recv(timeout=0)
            if now - last < 0.01:
                continue
            dt, last = now - last, now
            vl = left.sign * left.velocity(now) * circ_m
            vr = right.sign * right.velocity(now) * circ_m
            for a in (left, right):
                a.pos += a.velocity(now) * dt
            v, w = (vl + vr) / 2, (vr - vl) / (args.wheel_base_mm / 1000)
            x, y, th = x + v * math.cos(th) * dt, y + v * math.sin(th) * dt, th + w * dt
            tick += 1
            for a in (left, right):
                bus.send(can.Message(arbitration_id=a.node << 5 | 0x09, is_extended_id=False,
                                     data=struct.pack("<ff", a.pos, a.velocity(now))))
                if tick % 10 == 0:
                    bus.send(can.Message(arbitration_id=a.node << 5 | 0x01, is_extended_id=False,
                                         data=struct.pack("<IBBBB", a.error, a.state, 0, 0, 0)))
            if tick % 5 == 0:  # qnav's range and bumper boards at 20 Hz: an empty field
                n = tick // 5
                for i, m in enumerate(ranges):
                    sig = {f"Rng{i}_Counter": n % 256}
                    for k in range(4 * i, 4 * i + 4):
                        sig[f"Range{k}"], sig[f"Range{k}Status"] = 2000, too_far
                    bus.send(can.Message(arbitration_id=m.frame_id, is_extended_id=False, data=m.encode(sig)))
                sig = {s.name: 0 for s in bumper.signals}
                sig["Bump_Counter"] = n % 256
                bus.send(can.Message(arbitration_id=bumper.frame_id, is_extended_id=False, data=bumper.encode(sig)))
    except KeyboardInterrupt:
        pass
    finally:
        bus.shutdown()
    end = {"pose": [x, y, math.degrees(th)], "axes": {str(a.node): {"state": a.state, "error": a.error,
                                                                     "received": a.received} for a in (left, right)}}
    print(json.dumps(end))
    if args.json:
        Path(args.json).write_text(json.dumps(end))
    return 0


if __name__ == "__main__":
    sys.exit(main())
