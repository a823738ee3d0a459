"""A trivial lockstep controller for tests, benchmarks and demos of the plant.

Not the robot's controller (that is `firmware_py`): it drives forward until
a front sensor sees something within `stop_mm`, then turns left, and answers
every SimTick with a MotorCommand carrying the tick's counter, exactly as
docs/can-protocol.md asks of a controller (a repeated tick gets the same
answer again). `ReflexDriver.handle(msg)` is the pure core; `serve()` is the
bus shell; `python -m ground_station.lab.rigs.reflex --can SPEC` runs it as a process.
"""

from __future__ import annotations

import argparse
import sys
import threading

import can

from firmware_py import can_protocol as cp
from firmware_py import robot_spec

FRONT_SENSORS = (0, 1, robot_spec.SENSOR_COUNT - 1)


class ReflexDriver:
    def __init__(self, stop_mm: int = 400) -> None:
        self.stop_mm = stop_mm
        self.ranges: dict[int, tuple[int, int]] = {}
        self.last_tick: int | None = None
        self.last_answer: can.Message | None = None
        self.ticks = 0
        self.sim_time_us = 0

    def handle(self, msg: can.Message) -> list[can.Message]:
        aid = msg.arbitration_id
        if aid in cp.RANGE_SECTORS_IDS:
            self.ranges.update(cp.ranges_from(*cp.decode(msg)))
            return []
        if aid != cp.SIM_TICK_ID:
            return []
        _, sig = cp.decode(msg)
        tick = sig["Tick_Counter"]
        if tick == self.last_tick and self.last_answer is not None:
            return [self.last_answer]  # retransmitted tick: same answer, no new step
        self.sim_time_us = sig["Tick_SimTimeUs"]
        blocked = any(
            status == robot_spec.RANGE_TOO_CLOSE or (status == robot_spec.RANGE_VALID and mm < self.stop_mm)
            for mm, status in (self.ranges.get(i, (0, robot_spec.RANGE_TOO_FAR)) for i in FRONT_SENSORS))
        action = 1 if blocked else 0  # turn_left / forward
        left, right = robot_spec.ACTION_WHEEL_SPEEDS_MM_S[action]
        self.last_tick = tick
        self.last_answer = cp.motor_command(left, right, tick)
        self.ticks += 1
        return [self.last_answer]


def serve(bus: can.BusABC, driver: ReflexDriver, stop: threading.Event,
          max_ticks: int | None = None) -> int:
    """Answer ticks until `stop` is set or `max_ticks` ticks were answered."""
    while not stop.is_set() and (max_ticks is None or driver.ticks < max_ticks):
        msg = bus.recv(timeout=0.1)
        if msg is None:
            continue
        for reply in driver.handle(msg):
            bus.send(reply)
    return driver.ticks


def main(argv: list[str] | None = None) -> int:
    from firmware_py.canbus import CanSpecError, open_bus

    ap = argparse.ArgumentParser(prog="python -m ground_station.lab.rigs.reflex", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--can", default=None, help="bus spec, e.g. remote:ws://127.0.0.1:PORT/")
    ap.add_argument("--ticks", type=int, default=None, help="exit after answering this many ticks")
    ap.add_argument("--stop-mm", type=int, default=400, help="turn when a front reading is below this")
    args = ap.parse_args(argv)
    try:
        bus = open_bus(args.can)
    except CanSpecError as exc:
        print(f"reflex: error: {exc}", file=sys.stderr)
        return 2
    try:
        n = serve(bus, ReflexDriver(args.stop_mm), threading.Event(), args.ticks)
    except KeyboardInterrupt:
        n = -1
    finally:
        bus.shutdown()
    print(f"answered {n} ticks")
    return 0


if __name__ == "__main__":
    sys.exit(main())
