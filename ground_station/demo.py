"""The one-command demo (`qnav demo`): the whole system on one machine.

This module owns only the orchestration (`run_demo`), every step the
project's own piece used as an operator would: a CAN hub, `qnav-sim` and
`qnav-robot` as processes, one ground-station `Link`, policy and map uploaded
over MAVLink FTP, the mission, arm and Auto, the monitor (or headless its
`VehicleView`) until the mission ends, faults, a process dies or the timeout
passes; then every process stopped, whatever happened, and the files summarised.

The sim runs faster than real time in lockstep (tens of times), while the
robot measures its GCS failsafe and its mission transfer timeouts on sim
time: the ground station therefore sends its heartbeat every 50 ms of wall
time there and raises FS_GCS_TOUT_MS, MIS_TIMEOUT_MS and MIS_RETRIES to
their maxima, so a scheduling hiccup on a busy machine does not trip the
failsafe mid-mission or cancel the mission upload.
"""

from __future__ import annotations

import contextlib
import csv
import json
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

from firmware_py.atomic import atomic_write
from firmware_py.mavlink.params import PARAMS
from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec
from ground_station.mavlink.statustext import StatusTextAssembler, holds_for_good
from ground_station.processes import ProcessGroup, qnav_robot, qnav_sim
from ground_station.subprocs import free_udp_port

SHIPPED_POLICY = "policies:paper10_cell"  # firmware_py.shipped_policies spec
DEFAULT_TARGETS = ("A", "B", "C", "D")
DEFAULT_MAP = "paper10"
ACTIVE_REMOTE_DIR = "/policies"

EXIT_OK, EXIT_FAILED, EXIT_INTERRUPTED = 0, 1, 130
LOCKSTEP_HEARTBEAT_S = 0.05  # wall; ~1-2 s of robot time at the lockstep's 20-35x
REALTIME_HEARTBEAT_S = 1.0
# robot-clock timeouts raised to the robot's own bounds in lockstep (module docstring)
LOCKSTEP_PARAMS = {name: next(p.max for p in PARAMS if p.name == name)
                   for name in ("FS_GCS_TOUT_MS", "MIS_TIMEOUT_MS", "MIS_RETRIES")}
MAV_MISSION_STATE_COMPLETE = 5


class DemoError(Exception):
    """A step of the demo failed; the text is one line naming the step."""


@dataclass
class DemoOptions:
    map_name: str = DEFAULT_MAP
    targets: tuple[str, ...] = DEFAULT_TARGETS
    policy: Path | str | None = None  # a file or policies:NAME; None: the shipped paper10 policy (or a trained one)
    train: bool = False
    train_steps: int = 3_000_000
    realtime: bool = False
    headless: bool = False
    out: Path | None = None  # None: runs/demo-<timestamp>/
    timeout_s: float | None = None  # wall seconds for the mission; None: 120 lockstep, 400 real time
    seed: int = 0  # the sim's noise seed (and the obstacles' placement)
    obstacles: int = 0  # unmapped static discs on or beside the planned path (ground_station/nav/obstacles.py)
    movers: int = 0  # moving discs
    plan: bool | None = None  # send the planner's waypoints; None: for sector policies
    profile: Path | None = None  # a robot profile (firmware_py/profile.py): the robot and the sim use its backends

    def mission_timeout_s(self) -> float:
        if self.timeout_s is not None:
            return self.timeout_s
        return 400.0 if self.realtime else 120.0


@dataclass
class DemoSummary:
    ok: bool = False
    result: str = ""
    targets: list[str] = field(default_factory=list)
    targets_reached: int = 0
    targets_total: int = 0
    mission_items: int = 0  # waypoints sent (more than the targets when planned)
    planned: bool = False
    scenario: dict | None = None  # the unmapped obstacles (discs, movers; mm), also in scenario.json
    collisions: int | None = None
    sim_seconds: float | None = None  # robot (sim) time from the first move to the last target
    wall_seconds: float = 0.0  # the whole demo, start-up to shut-down
    mission_wall_seconds: float | None = None  # Auto to the last target
    telemetry_loss_pct: float | None = None  # MAVLink frames from the robot lost (sequence gaps)
    mode: str = "lockstep"
    map: str = ""
    policy: str = ""
    policy_id: str | None = None
    upload_seconds: float | None = None
    run_dir: str = ""
    can_hub: str | None = None  # the python-can-remote hub's URL (stopped at the end)
    tlog: str | None = None
    can_log: str | None = None
    can_log_candump: str | None = None  # can.log: the .blf's frames in candump -L format
    trajectory_png: str | None = None
    trajectory_csv: str | None = None
    robot_stats: str | None = None
    mcap: str | None = None  # run.mcap: the whole run for Foxglove, PlotJuggler, Rerun (ground_station/logs)
    logs: dict[str, str] = field(default_factory=dict)
    exit_codes: dict[str, int | None] = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1)


# --- small helpers ---------------------------------------------------------------
def default_run_dir(prefix: str = "demo", base: Path = Path("runs")) -> Path:
    """runs/PREFIX-<timestamp>/ (then -2, -3, ... beside one that exists): the run folder of
    `qnav demo` and, with prefix "sitl" or a run's name, of `qnav sitl` and `qnav train`."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    path, n = base / f"{prefix}-{stamp}", 1
    while path.exists():
        n += 1
        path = base / f"{prefix}-{stamp}-{n}"
    return path


def start_cell(occ) -> tuple[int, int]:
    """The free cell nearest the map centre (the sim's own default start)."""
    height, width = occ.shape
    cy, cx = (height - 1) / 2, (width - 1) / 2
    free = [(r, c) for r in range(height) for c in range(width) if not occ[r, c]]
    if not free:
        raise DemoError("the map has no free cell to start in")
    row, col = min(free, key=lambda rc: ((rc[0] - cy) ** 2 + (rc[1] - cx) ** 2, rc))
    return col, row


def count_collisions(trajectory_csv: Path) -> int:
    """Contacts in the sim's ground-truth trajectory: rising edges of its bumper column."""
    count, last = 0, 0
    with open(trajectory_csv, newline="") as f:
        for row in csv.DictReader(f):
            pressed = int(float(row["bumper"])) != 0
            if pressed and not last:
                count += 1
            last = pressed
    return count


def mission_sim_seconds(robot_stats: Path) -> float | None:
    """Robot (sim) time from the first DRIVING to "mission complete", from the
    controller's own transition record (`qnav-robot --stats-json`)."""
    try:
        transitions = json.loads(robot_stats.read_text())["transitions"]
    except (OSError, ValueError, KeyError):
        return None
    start = next((t for t, _src, dst, _cause in transitions if dst == "DRIVING"), None)
    end = next((t for t, _src, _dst, cause in transitions if cause == "mission complete"), None)
    if start is None or end is None:
        return None
    return (end - start) / 1e6


class MissionWatch:
    """Follows the mission from every frame the link parses (a pymavlink message hook, so frames
    another reader consumes count too): targets reached, robot time, a controller FAULT."""

    def __init__(self, total: int, target_seqs: list[int] | None = None) -> None:
        self.total = total  # mission items
        self.target_seqs = list(target_seqs) if target_seqs is not None else list(range(total))
        self.reached: set[int] = set()
        self.boot_ms: int | None = None  # latest robot time seen (LOCAL_POSITION_NED)
        self.mission_state = 0
        self.fault = ""
        self.stopped = ""  # the robot stopped driving for good (bumper or stall -> HOLD)
        self.texts: list[str] = []
        self._assembler = StatusTextAssembler()
        self.start_ms: int | None = None
        self.start_wall: float | None = None
        self.done_ms: int | None = None
        self.done_wall: float | None = None
        self.sysid: int | None = None

    def hook(self, _conn, msg) -> None:
        kind = msg.get_type()
        if self.sysid is not None and msg.get_srcSystem() != self.sysid:
            return
        if kind == "LOCAL_POSITION_NED":
            self.boot_ms = msg.time_boot_ms
        elif kind == "MISSION_ITEM_REACHED":
            if self.start_wall is not None:
                self.reached.add(msg.seq)
        elif kind == "MISSION_CURRENT":
            self.mission_state = msg.mission_state
            if self.start_wall is not None:
                # periodic, so a lost MISSION_ITEM_REACHED is made up: items
                # before the current one are done, all of them once COMPLETE
                done = msg.total if msg.mission_state == MAV_MISSION_STATE_COMPLETE else msg.seq
                self.reached.update(range(min(done, self.total)))
        elif kind == "NAMED_VALUE_INT":
            from ground_station.monitor.model import NV_CTRL_STATE, field_text

            if field_text(msg.name) == NV_CTRL_STATE:
                from firmware_py.vehicle import CtrlState

                if msg.value == CtrlState.FAULT and not self.fault:
                    self.fault = "controller FAULT" + (f" ({self.texts[-1]})" if self.texts else "")
        elif kind == "STATUSTEXT":  # whole texts, as every other reader sees them
            for st in self._assembler.add(msg, time.monotonic()):
                self.texts.append(st.text)
                # the controller holds for good (bumper, or NAV_STALL_S without progress): waiting out
                # the timeout tells nothing
                if self.start_wall is not None and not self.stopped and holds_for_good(st.text):
                    self.stopped = f"stopped: {st.text}"
        if self.complete and self.done_wall is None:
            self.done_wall = time.monotonic()
            self.done_ms = self.boot_ms

    def started(self) -> None:
        self.start_wall = time.monotonic()
        self.start_ms = self.boot_ms

    @property
    def complete(self) -> bool:
        return self.start_wall is not None and len(self.reached) >= self.total

    @property
    def targets_reached(self) -> int:
        """Targets done (items that end a planned leg, or every item)."""
        return sum(seq in self.reached for seq in self.target_seqs)

    @property
    def sim_seconds(self) -> float | None:
        return None if self.done_ms is None or self.start_ms is None else (self.done_ms - self.start_ms) / 1000

    @property
    def mission_wall_seconds(self) -> float | None:
        return None if self.done_wall is None or self.start_wall is None else self.done_wall - self.start_wall


class ThreadedSource:
    """A `LiveSource` whose frames a background thread reads as they arrive: in lockstep a
    dashboard reading the socket only between redraws lets the kernel's UDP buffer overflow.
    The LiveSource keeps its other duties (GCS heartbeat, POLICY_ID requests), run from `poll`."""

    finished = False

    def __init__(self, live) -> None:
        self.live = live
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="demo-mavlink-rx", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        conn = self.live.conn
        while not self._stop.is_set():
            try:
                msg = conn.recv_match(blocking=True, timeout=0.05)
            except (OSError, ValueError):
                if self._stop.wait(0.05):
                    return
                continue
            if msg is not None and msg.get_type() != "BAD_DATA":
                self._queue.put((msg, self.live.now()))

    def now(self) -> float:
        return self.live.now()

    def poll(self, limit: int = 2000) -> list[tuple[object, float]]:
        self.live.poll(limit=0)  # heartbeat / parameter duties only; the thread reads
        out: list[tuple[object, float]] = []
        while len(out) < limit:
            try:
                out.append(self._queue.get_nowait())
            except queue.Empty:
                break
        return out

    def send_command(self, kind: str, target: tuple[int, int]) -> str:
        return self.live.send_command(kind, target)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)


# --- the steps ---------------------------------------------------------------------
@contextlib.contextmanager
def _link_step(what: str = "") -> Iterator[None]:
    """A LinkError in the block ends the demo as a DemoError: `what`, then the link's one line."""
    from ground_station.mavlink.link import LinkError

    try:
        yield
    except LinkError as exc:
        raise DemoError(f"{what}{exc}") from None


def train_policy(opts: DemoOptions, run_dir: Path, say: Callable[[str], None]) -> Path:
    """Train (progress bar) and export an int8 cell policy into the run folder."""
    from firmware_py.policy import PolicyError, load_policy
    from ground_station.learn import export
    from ground_station.learn.train import TrainConfig, train, validate_config, write_run
    from ground_station.maps import load_map

    cfg = TrainConfig.of(map=opts.map_name, encoding="cell", targets=",".join(opts.targets),
                      steps=opts.train_steps, seed=0)
    validate_config(cfg)
    say(f"training a cell policy on {opts.map_name}, targets {cfg.options.targets}, {cfg.steps:,} steps")
    res = train(cfg, load_map(cfg.map), progress=True)
    train_dir = run_dir / "train"
    write_run(train_dir, cfg, res)
    run = export.load_run(train_dir)
    qt = export.quantise(run.q, "int8", preserve_argmax=True)  # the float table's greedy choice (qnav export)
    data = export.policy_bytes(qt, run.encoder, goals=run.goals, cell_mm=run.cell_mm,
                               metadata=export.file_metadata(run, qt), created=export.created_time(run.meta),
                               control_period_us=export.control_period_us(run), map_geometry=export.map_geometry(run))
    try:
        load_policy(data)  # the robot's loader judges the file before it flies
    except PolicyError as exc:
        raise DemoError(f"exported policy fails the robot's loader: {exc}") from None
    out = run_dir / "policy.qtab"
    atomic_write(out, data)
    say(f"exported {out} ({len(data)} B, int8)")
    return out


def _upload(link, policy: Path, say: Callable[[str], None], quiet: bool) -> tuple[float, str | None]:
    from tqdm import tqdm

    from ground_station.mavlink.ftp_upload import upload_policy

    size = policy.stat().st_size
    remote = f"{ACTIVE_REMOTE_DIR}/upload-{policy.name}"
    with tqdm(total=size, unit="B", unit_scale=True, desc=f"upload {policy.name}", disable=quiet or None,
              file=sys.stderr) as bar:
        def progress(frac):
            if frac is not None:
                bar.n = int(frac * size)
                bar.refresh()

        with _link_step("policy upload: "):
            res = upload_policy(link, policy, remote, activate=True, deadline_s=120.0, progress=progress)
        bar.n = size
    pid = f"0x{res.policy_id:08x}" if res.policy_id is not None else None
    say(f"uploaded {policy.name} ({res.size} B, CRC 0x{res.crc:08x}) in {res.put_seconds:.1f} s, "
        f"activated: policy id {pid}, confirmed by {res.confirmed_by}")
    return res.put_seconds, pid


def _upload_map(link, grid_map, run_dir: Path, say: Callable[[str], None]) -> None:
    """The map the sim plays becomes the robot's own (`qnav map upload`): it localises and plans
    on the world it is in, whatever map its policy was trained on."""
    from ground_station.maps import write_map
    from ground_station.mavlink.ftp_upload import upload_map

    local = run_dir / "robot_map.map"
    write_map(local, grid_map)
    with _link_step("map upload: "):
        res = upload_map(link, local, deadline_s=60.0)
    say(f"map {grid_map.name} uploaded and active on the robot ({res.size} B), confirmed by {res.confirmed_by}")


def mission_plan(opts: DemoOptions, grid_map, start_mm: tuple[float, float], planned: bool,
                 plan_kw: dict | None = None) -> tuple[list[tuple[int, int, int]], list[int]]:
    """(mission items, item index of each target): the targets' centres, or planned waypoints."""
    from ground_station.mavlink.mission_items import planned_items, target_cells, target_items

    if planned:
        return planned_items(target_cells(",".join(opts.targets), grid_map), start_mm, grid_map, plan_kw)
    items = target_items(",".join(opts.targets), grid_map)
    return items, list(range(len(items)))


def demo_scenario(opts: DemoOptions, grid_map, start_mm: tuple[float, float],
                  items: list[tuple[int, int, int]]) -> dict:
    """Seeded unmapped obstacles: up to `obstacles` detourable discs along the mission path and
    `movers` movers (`ground_station.nav.obstacles`, as the benchmark places them)."""
    import numpy as np

    from firmware_py.mavlink.frames import LOCAL_ITEM_SCALE
    from ground_station.nav.obstacles import place_discs, place_movers

    rng = np.random.default_rng(opts.seed)
    per_mm = LOCAL_ITEM_SCALE / 1000  # LOCAL_NED item units per world mm
    wps = [(east / per_mm, north / per_mm) for _f, north, east in items]
    discs = place_discs(grid_map, start_mm, wps, opts.obstacles, rng)
    movers = place_movers(grid_map, start_mm, discs, opts.movers, rng)
    return {"map": grid_map.name, "seed": opts.seed, "discs": discs, "movers": movers,
            "definition": "ground_station/nav/obstacles.py"}


def _command_mission(link, opts: DemoOptions, say: Callable[[str], None],
                     items: list[tuple[int, int, int]]) -> None:
    with _link_step():
        n = link.mission_upload(items)
        say(f"mission {' -> '.join(opts.targets)} accepted ({n} waypoints)")
        link.command(link.m.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        say("armed")


def _set_auto(link, say: Callable[[str], None]) -> None:
    from firmware_py.vehicle import Mode

    m = link.m
    with _link_step():
        link.command(m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(Mode.AUTO))
    say("mode Auto: driving the mission")


def _wait_headless(source, view, watch: MissionWatch, procs: ProcessGroup, deadline: float,
                   status: Callable[[str], None] | None) -> str:
    next_line = time.monotonic() + 1.0
    while True:
        batch = source.poll()
        for msg, t in batch:
            view.update(msg, t)
        verdict = _verdict(watch, procs, deadline)
        if verdict:
            return verdict
        if status is not None and time.monotonic() >= next_line:
            status(view.status_line(source.now()))
            next_line += 1.0
        if not batch:
            time.sleep(0.02)


def _verdict(watch: MissionWatch, procs: ProcessGroup, deadline: float) -> str:
    """Why the wait is over ("" while it is not)."""
    if watch.complete:
        return "mission complete"
    if watch.fault:
        return watch.fault
    if watch.stopped:
        return watch.stopped
    dead = procs.dead()
    if dead:
        return "; ".join(f"{name} exited with status {code}" for name, code in dead)
    if time.monotonic() >= deadline:
        return (f"timeout: only {watch.targets_reached} of {len(watch.target_seqs)} targets reached "
                "within the mission timeout")
    return ""


def _wait_tui(source, view, grid_map, watch: MissionWatch, procs: ProcessGroup, deadline: float,
              subtitle: str) -> str:
    from textual.binding import Binding

    from ground_station.monitor.app import MonitorApp

    class DemoMonitor(MonitorApp):
        TITLE = "qnav demo"
        BINDINGS = [*MonitorApp.BINDINGS, Binding("ctrl+c", "quit", "quit", show=False)]
        verdict = ""
        closing_at = 0.0

        def pump(self) -> None:
            super().pump()
            if not self.verdict:
                self.verdict = _verdict(watch, procs, deadline)
                if self.verdict:
                    self.sub_title = f"{self.verdict} - closing"
                    # leave the final picture up a moment; after a completed mission until the robot's
                    # own "mission complete" line (it can trail MISSION_ITEM_REACHED), 10 s at most
                    self.closing_at = time.monotonic() + (10.0 if self.verdict == "mission complete" else 2.0)
                    self.set_timer(2.0, self.close_when_shown)

        def close_when_shown(self) -> None:
            if time.monotonic() >= self.closing_at or any("mission complete" in e.text for e in self.view.log):
                self.exit()
            else:
                self.set_timer(0.25, self.close_when_shown)

    app = DemoMonitor(source, grid_map=grid_map, view=view, subtitle=subtitle)
    app.run()
    return app.verdict or "monitor closed by the user"


def _write_mcap(out: Path, paths: dict[str, Path], grid_map, say: Callable[[str], None]) -> str | None:
    """The run as one MCAP (ground_station/logs/mcap_run.py); None, said, if it cannot be written."""
    from ground_station.logs.mcap_run import McapError, write_run_mcap

    robot_log = out.parent / "robot.log"
    try:
        write_run_mcap(out, paths["tlog"], can_log=paths["can_log"] if paths["can_log"].is_file() else None,
                       trajectory=paths["trajectory_csv"] if paths["trajectory_csv"].is_file() else None,
                       grid_map=grid_map, robot_log=robot_log if robot_log.is_file() else None)
    except (McapError, OSError, ValueError) as exc:
        say(f"run.mcap not written: {exc}")
        return None
    except Exception as exc:  # noqa: BLE001 - a converter bug must not cut the demo's clean-up short
        say(f"run.mcap not written: {type(exc).__name__}: {exc}")
        return None
    return str(out)


def run_demo(opts: DemoOptions, say: Callable[[str], None] | None = None,
             status: Callable[[str], None] | None = None) -> DemoSummary:
    """Run the whole demo; the summary (also written to the run folder). `say` gets one line per
    step, `status` (headless) a monitor status line per second. Bad options raise DemoError
    before anything starts; a later failed step ends the run with `result` "error: ...", Ctrl-C
    with "interrupted", after the same clean-up."""
    say = say or (lambda _line: None)
    t0 = time.monotonic()
    from ground_station.canhub import CanHub
    from ground_station.errors import CliError
    from ground_station.maps import MapError, load_map
    from ground_station.mavlink.link import Link
    from ground_station.monitor.model import VehicleView
    from ground_station.monitor.sources import LiveSource

    try:
        grid_map = load_map(opts.map_name)
    except (MapError, OSError) as exc:
        raise DemoError(f"map {opts.map_name}: {exc}") from None
    missing = [t for t in opts.targets if t not in grid_map.targets]
    if missing:
        raise DemoError(f"map {grid_map.name} has no target {', '.join(missing)} "
                        f"(has {', '.join(sorted(grid_map.targets))})")

    try:
        policy = resolve_policy_spec(opts.policy or SHIPPED_POLICY)
    except ShippedPolicyError as exc:
        raise DemoError(f"policy {opts.policy or SHIPPED_POLICY}: {exc}") from None
    if not opts.train and not policy.is_file():
        raise DemoError(f"policy {policy}: no such file")
    plan_kw: dict = {}
    planned = bool(opts.plan)
    if not opts.train:
        from firmware_py.policy import PolicyError, load_policy
        from ground_station.maps.planner import guidance_from_metadata

        try:
            pol = load_policy(str(policy))
        except PolicyError:
            pol = None  # the robot's loader judges it on upload and gives the reason
        if pol is not None and opts.plan is None:  # a sector policy steers to the planner's waypoints
            planned = pol.kind == "sector"
        if pol is not None and pol.kind == "sector":
            plan_kw = guidance_from_metadata(pol.metadata)
    if opts.profile is not None:  # the planner keeps the profile's body clear, as its trainer did
        from ground_station.maps.planner import profile_radius_mm

        try:
            plan_kw["radius_mm"] = profile_radius_mm(opts.profile)
        except ValueError as exc:
            raise DemoError(f"--profile {exc}") from None

    run_dir = Path(opts.out) if opts.out else default_run_dir()
    run_dir.mkdir(parents=True, exist_ok=True)
    summary = DemoSummary(targets=list(opts.targets), targets_total=len(opts.targets),
                          mode="real time" if opts.realtime else "lockstep", run_dir=str(run_dir),
                          map=grid_map.name)
    if opts.train:
        policy = train_policy(opts, run_dir, say)
    summary.policy = str(policy)

    col, row = start_cell(grid_map.occ)
    x, y = grid_map.cell_size_m * (col + 0.5), grid_map.cell_size_m * (grid_map.height - row - 0.5)
    start = f"{x:g},{y:g},0"
    try:
        items, target_seqs = mission_plan(opts, grid_map, (x * 1000, y * 1000), planned, plan_kw)
    except CliError as exc:
        raise DemoError(f"mission: {exc}") from None
    summary.mission_items, summary.planned = len(items), planned
    scenario_file = None
    if opts.obstacles > 0 or opts.movers > 0:
        summary.scenario = demo_scenario(opts, grid_map, (x * 1000, y * 1000), items)
        scenario_file = run_dir / "scenario.json"
        atomic_write(scenario_file, json.dumps(summary.scenario, indent=1) + "\n")
        say(f"unmapped obstacles: {len(summary.scenario['discs'])} discs, {len(summary.scenario['movers'])} "
            f"movers ({scenario_file})")
    paths = {
        "tlog": run_dir / "demo.tlog", "can_log": run_dir / "can.blf",
        "trajectory_csv": run_dir / "trajectory.csv", "trajectory_png": run_dir / "trajectory.png",
        "robot_stats": run_dir / "robot_stats.json",
    }
    logs = {"sim": run_dir / "sim.log", "robot": run_dir / "robot.log"}
    summary.logs = {k: str(v) for k, v in logs.items()}
    storage = run_dir / "robot"
    storage.mkdir(exist_ok=True)

    procs = ProcessGroup()
    hub = CanHub(channel="qnav-demo")
    link = None
    verdict = ""
    try:
        try:
            hub.start()
        except RuntimeError as exc:
            raise DemoError(f"CAN hub: {exc}") from None
        summary.can_hub = hub.url
        say(f"CAN hub {hub.url} (python-can-remote)")
        port = free_udp_port()
        link = Link(f"udpin:127.0.0.1:{port}", tlog=paths["tlog"], name="demo")
        summary.tlog = str(paths["tlog"])
        sim_argv = qnav_sim("--map", opts.map_name, "--can", hub.spec,
                            "--start", start, "--seed", str(opts.seed), "--log", str(paths["can_log"]),
                            "--trajectory", str(paths["trajectory_csv"]), "--png", str(paths["trajectory_png"]),
                            "-q", die_with_parent=True)
        if scenario_file is not None:
            sim_argv += ["--scenario", str(scenario_file)]
        if opts.profile is not None:
            sim_argv += ["--profile", str(opts.profile)]
        if opts.realtime:
            sim_argv += ["--realtime", "--duration", f"{opts.mission_timeout_s() + 300:g}"]
        else:
            sim_argv += ["--lockstep", "--duration", "36000", "--start-timeout", "60"]
        robot_argv = qnav_robot("--can", hub.spec,
                                "--lockstep" if not opts.realtime else "--sim-clock", "--start", start,
                                "--storage", str(storage), "--mavlink", f"udpout:127.0.0.1:{port}",
                                "--stats-json", str(paths["robot_stats"]),
                                # the demo's plant is ideal (exact encoders): dead reckoning is exact, and
                                # the localiser's corridor jitter (~0.1 m) could clip a corner
                                "--localiser", "off",
                                *(["--profile", str(opts.profile)] if opts.profile is not None else []),
                                die_with_parent=True)
        procs.start("sim", sim_argv, logs["sim"])
        procs.start("robot", robot_argv, logs["robot"])
        say(f"qnav-sim ({summary.mode}) and qnav-robot started, start cell ({col}, {row}); "
            f"MAVLink udp 127.0.0.1:{port}; logs in {run_dir}")

        try:
            link.connect(30.0)
        except Exception as exc:
            dead = procs.dead()
            why = "; ".join(f"{n} exited with status {c} (see {logs[n]})" for n, c in dead) or str(exc)
            raise DemoError(f"robot not reachable over MAVLink: {why}") from None
        watch = MissionWatch(len(items), target_seqs)
        watch.sysid = link.sysid
        link.conn.message_hooks.append(watch.hook)
        link.start_heartbeat(REALTIME_HEARTBEAT_S if opts.realtime else LOCKSTEP_HEARTBEAT_S)
        say(f"robot sysid {link.sysid} found")
        if not opts.realtime:
            for name, value in LOCKSTEP_PARAMS.items():
                with _link_step(f"{name}: "):
                    link.param_set(name, value)

        summary.upload_seconds, summary.policy_id = _upload(link, policy, say, quiet=False)
        _upload_map(link, grid_map, run_dir, say)
        _command_mission(link, opts, say, items)
        watch.started()
        _set_auto(link, say)

        source = ThreadedSource(LiveSource(link))
        view = VehicleView(sysid=link.sysid)
        deadline = time.monotonic() + opts.mission_timeout_s()
        try:
            if opts.headless:
                verdict = _wait_headless(source, view, watch, procs, deadline, status)
            else:
                verdict = _wait_tui(source, view, grid_map, watch, procs, deadline,
                                    subtitle=f"{summary.mode}  {' -> '.join(opts.targets)}  {run_dir}")
        finally:
            source.close()
        say(verdict)
        summary.targets_reached = watch.targets_reached
        summary.sim_seconds = watch.sim_seconds
        summary.mission_wall_seconds = watch.mission_wall_seconds
        summary.telemetry_loss_pct = round(view.link.loss_pct, 2)
    except DemoError as exc:  # a step failed: the summary says which, the processes still stop
        verdict = f"error: {exc}"
    except KeyboardInterrupt:  # Ctrl-C (or SIGTERM, see commands/demo.py): clean up, report what happened
        verdict = "interrupted"
    finally:
        # a second Ctrl-C must not cut the clean-up short and leave processes behind
        in_main = threading.current_thread() is threading.main_thread()
        previous_sigint = signal.signal(signal.SIGINT, signal.SIG_IGN) if in_main else None
        summary.result = verdict
        if link is not None:
            link.stop_heartbeat()
        summary.exit_codes = procs.stop_all()
        if link is not None:
            link.close()
        hub.stop()
        for key, path in paths.items():
            setattr(summary, key, str(path) if path.is_file() else None)
        if paths["can_log"].is_file():  # the same frames as candump -L text, for cantools decode / canplayer
            from ground_station.monitor.canlog import write_candump

            candump = paths["can_log"].with_suffix(".log")
            with contextlib.suppress(OSError, ValueError):
                write_candump(paths["can_log"], candump)
                summary.can_log_candump = str(candump)
        if paths["trajectory_csv"].is_file():
            summary.collisions = count_collisions(paths["trajectory_csv"])
        if paths["tlog"].is_file():
            summary.mcap = _write_mcap(run_dir / "run.mcap", paths, grid_map, say)
        exact = mission_sim_seconds(paths["robot_stats"])
        if exact is not None and summary.targets_reached:
            summary.sim_seconds = exact
        summary.wall_seconds = time.monotonic() - t0
        summary.ok = (verdict == "mission complete" and summary.targets_reached == summary.targets_total
                      and summary.collisions == 0)
        with contextlib.suppress(OSError):
            atomic_write(run_dir / "summary.json", summary.to_json() + "\n")
        if previous_sigint is not None:
            signal.signal(signal.SIGINT, previous_sigint)
    return summary
