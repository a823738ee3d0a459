"""`qnav bench sim`: how fast the pymunk plant runs.

* `rtf`: physics (fixed `robot_spec.PHYSICS_DT_US` steps) + all sensors sampled
  and encoded into CAN frames at the control rate (20 Hz), driven by the
  reflex controller called directly (no bus), as sim seconds per wall second.
  Baseline: real time (1.0).
* `lockstep_ticks_per_s_inprocess`: the full lockstep handshake on a python-can
  `virtual` bus, plant in the main thread, reflex controller in a thread.
* `lockstep_ticks_per_s_remote`: the same across processes — the plant here,
  the reflex controller in its own process (`ground_station.lab.rigs.reflex`),
  both on a python-can-remote hub on 127.0.0.1 (a third process).

Tick rates are compared with the real-time control rate (20 ticks/s) and the
remote one also with the in-process one, all measured in this run.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
import uuid

from firmware_py import robot_spec

MAP_DEFAULT = "paper10"


def add_subparser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="plant speed: real-time factor, lockstep ticks/s in-process and remote",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--map", default=MAP_DEFAULT, metavar="NAME|PATH", help="map (default paper10)")
    p.add_argument("--sim-seconds", type=float, default=120.0, help="sim seconds for the rtf figure")
    p.add_argument("--ticks", type=int, default=3000, help="lockstep ticks per transport")
    p.add_argument("--json", metavar="FILE", help="write the result as JSON")
    p.set_defaults(func=run)


def _plant(occ, cell_size_m: float):
    from sim_bridge.plant import Plant, SimConfig

    return Plant(occ, SimConfig(seed=1, cell_size_m=cell_size_m))


def measure_rtf(occ, cell_size_m: float, sim_seconds: float) -> dict:
    from ground_station.lab.rigs.reflex import ReflexDriver

    plant = _plant(occ, cell_size_m)
    driver = ReflexDriver()
    ticks = round(sim_seconds * 1e6 / robot_spec.CONTROL_PERIOD_US)
    t0 = time.perf_counter()
    for _ in range(ticks):
        for frame in plant.tick_frames():
            for reply in driver.handle(frame):
                plant.handle(reply)
        plant.step_period()
    wall = time.perf_counter() - t0
    steps = ticks * robot_spec.CONTROL_PERIOD_US // robot_spec.PHYSICS_DT_US
    return {"rtf": plant.time_us / 1e6 / wall, "physics_steps_per_s": steps / wall,
            "sim_s": plant.time_us / 1e6, "wall_s": wall, "contacts": plant.world.contact_events}


def measure_inprocess(occ, cell_size_m: float, ticks: int) -> dict:
    from firmware_py.canbus import open_bus
    from ground_station.lab.rigs.reflex import ReflexDriver, serve
    from sim_bridge.plant import run_lockstep

    channel = f"bench-sim-{uuid.uuid4().hex}"
    plant = _plant(occ, cell_size_m)
    bus, cbus = open_bus(f"virtual:{channel}"), open_bus(f"virtual:{channel}")
    stop = threading.Event()
    thread = threading.Thread(target=serve, args=(cbus, ReflexDriver(), stop))
    thread.start()
    try:
        stats = run_lockstep(plant, bus, ticks * robot_spec.CONTROL_PERIOD_US / 1e6)
    finally:
        stop.set()
        thread.join(5)
        bus.shutdown()
        cbus.shutdown()
    return {"ticks_per_s": stats.ticks_per_s, "ticks": stats.ticks, "missed": stats.missed_ticks}


def measure_remote(occ, cell_size_m: float, ticks: int) -> dict:
    from firmware_py.canbus import open_bus
    from ground_station.canhub import CanHub
    from ground_station.processes import ChildProcess, program_argv
    from sim_bridge.plant import run_lockstep

    plant = _plant(occ, cell_size_m)
    with CanHub("bench-sim") as hub:
        ctl = ChildProcess([*program_argv("ground_station.lab.rigs.reflex:main", "reflex"), "--can", hub.spec], None).start()
        bus = open_bus(hub.spec)
        try:
            stats = run_lockstep(plant, bus, ticks * robot_spec.CONTROL_PERIOD_US / 1e6,
                                 start_timeout_s=30.0)
        finally:
            bus.shutdown()
            ctl.stop(grace_s=10)
    frames = stats.frames_sent + stats.frames_received
    busy = stats.wall_s - stats.start_wait_s
    return {"ticks_per_s": stats.ticks_per_s, "ticks": stats.ticks, "missed": stats.missed_ticks,
            "frames_per_s": frames / busy if busy > 0 else 0.0}


def run(args: argparse.Namespace) -> int:
    from ground_station.errors import CliError
    from ground_station.lab.bench.common import report
    from ground_station.maps import MapError, load_map

    if args.sim_seconds <= 0 or args.ticks <= 0:
        raise CliError("--sim-seconds and --ticks must be positive")
    try:
        gm = load_map(args.map)
    except (MapError, OSError, ValueError) as exc:
        raise CliError(f"--map {args.map}: {exc}") from None
    print(f"map {gm.name} {gm.width}x{gm.height}; {args.sim_seconds:g} sim s for rtf, "
          f"{args.ticks} lockstep ticks per transport", file=sys.stderr)
    rtf = measure_rtf(gm.occ, gm.cell_size_m, args.sim_seconds)
    inproc = measure_inprocess(gm.occ, gm.cell_size_m, args.ticks)
    remote = measure_remote(gm.occ, gm.cell_size_m, args.ticks)
    realtime_ticks = 1e6 / robot_spec.CONTROL_PERIOD_US
    result = {
        "map": gm.name,
        "rtf": rtf["rtf"],
        "rtf_baseline": 1.0,
        "physics_steps_per_s": rtf["physics_steps_per_s"],
        "sensor_rate_hz": realtime_ticks,
        "lockstep_ticks_per_s_inprocess": inproc["ticks_per_s"],
        "lockstep_ticks_per_s_remote": remote["ticks_per_s"],
        "realtime_ticks_per_s": realtime_ticks,
        "inprocess_x_realtime": inproc["ticks_per_s"] / realtime_ticks,
        "remote_x_realtime": remote["ticks_per_s"] / realtime_ticks,
        "remote_vs_inprocess": remote["ticks_per_s"] / inproc["ticks_per_s"],
        "remote_frames_per_s": remote["frames_per_s"],
        "missed_ticks": inproc["missed"] + remote["missed"],
        "details": {"rtf": rtf, "inprocess": inproc, "remote": remote},
    }
    rows = [
        ("rtf (physics + sensors @ 20 Hz; baseline real time = 1)", result["rtf"]),
        ("physics_steps_per_s (dt 5 ms)", result["physics_steps_per_s"]),
        ("lockstep_ticks_per_s_inprocess (virtual bus)", result["lockstep_ticks_per_s_inprocess"]),
        ("  x real time (20 ticks/s)", result["inprocess_x_realtime"]),
        ("lockstep_ticks_per_s_remote (hub, 3 processes)", result["lockstep_ticks_per_s_remote"]),
        ("  x real time (20 ticks/s)", result["remote_x_realtime"]),
        ("  remote / in-process", result["remote_vs_inprocess"]),
        ("remote frames/s (sent + received by the plant)", result["remote_frames_per_s"]),
        ("missed ticks", result["missed_ticks"]),
    ]
    report("sim", rows, result, args.json)
    return 0
