"""`qnav sitl`: a simulated robot that stays up, as ArduPilot's sim_vehicle.py does.

Owns the bring-up of one vehicle for stock ground stations: a CAN bus (a
python-can-remote hub, or `--can`), `qnav-sim` paced at `speed` times real time
and `qnav-robot` on the sim's clock (`ProcessGroup`); then it waits for Ctrl-C,
`duration_s` or a child's death and stops every child (the hub last). Ground
stations connect with the strings `connection_help()` prints. On UDP a
`TlogRelay` records every frame into `mavlink.tlog` (run.mcap on stop). The
HEARTBEAT probe announces itself as an onboard controller (no GCS, so it arms
no failsafe); at `speed` > 1 it raises FS_GCS_TOUT_MS and MIS_TIMEOUT_MS by the
speed, since the robot measures them on sim time. docs/hil.md, "SITL".
"""

from __future__ import annotations

import errno
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from firmware_py.mavlink.params import PARAMS
from firmware_py.mavlink.telemetry import DEFAULT_AUTOPILOT
from firmware_py.shipped_policies import ShippedPolicyError, resolve_policy_spec
from ground_station.canhub import CanHub
from ground_station.demo import default_run_dir, start_cell
from ground_station.errors import CliError
from ground_station.mavlink.link import check_url
from ground_station.mavlink.tlog_relay import TlogRelay, relayable
from ground_station.processes import ProcessGroup, qnav_robot, qnav_sim

DEFAULT_MAP = "paper10"
DEFAULT_MAVLINK = "udpin:127.0.0.1:14555"  # the robot listens; GCSs connect to it (14550 stays free for QGC)
SHIPPED_FOR_MAP = {"paper10": "policies:paper10_cell"}
FALLBACK_POLICY = "policies:sector"  # observes ranges and bearings: runs on any map
PROGRESS_PERIOD_S = 1.0  # run.mcap progress lines on stop
SIM_DURATION_S = 30 * 24 * 3600  # the sim's own end: far away, the wait ends it
# the robot's timeouts on its own clock (sim time) that a ground station's wall-clock pace must meet:
# scaled by the speed at start, within the robot's own bounds (module docstring)
SPEED_SCALED_PARAMS = tuple(p for p in PARAMS if p.name in ("FS_GCS_TOUT_MS", "MIS_TIMEOUT_MS"))


class SitlError(CliError):
    """A bring-up step failed; the text names it (and the log to read)."""


@dataclass
class SitlOptions:
    map_name: str = DEFAULT_MAP
    policy: str | None = None  # a file or policies:NAME; None: shipped for the map; "none": no policy
    can: str | None = None  # None: start a python-can-remote hub
    speed: float = 1.0
    lockstep: bool = False  # the sim waits for every robot command, at most `speed` times real time
    mavlink: str = DEFAULT_MAVLINK
    out: Path | None = None  # None: runs/sitl-<timestamp>/
    seed: int = 0
    duration_s: float | None = None  # wall seconds, then stop (None: until Ctrl-C)
    autopilot: str = DEFAULT_AUTOPILOT  # the robot's HEARTBEAT autopilot (--mavlink-autopilot): "ardupilot" for MAVSDK
    probe_timeout_s: float = 60.0
    profile: Path | None = None  # a robot profile: the robot drives through its backends, the sim plays its boards


@dataclass
class SitlInfo:
    """What is up, for the connection help and for tests."""

    run_dir: Path
    mavlink: str  # the robot's own connection string
    gcs_url: str  # what a pymavlink-based GCS (MAVProxy, qnav) gives as its connection string
    can_spec: str
    hub: bool
    policy: str
    start: str
    sysid: int | None = None
    logs: dict[str, Path] = field(default_factory=dict)
    drive_backend: str = "qnav"  # the robot profile's backends (docs/robot-profile.md): what the bus carries
    sensor_backend: str = "qnav"


@dataclass(frozen=True)
class WaitResult:
    """Why `Sitl.wait` returned: `reason` to print; `child_died` (exit status 1) or --duration."""

    reason: str
    child_died: bool


def gcs_side(robot_url: str) -> str:
    """The connection string a ground station uses to reach a robot on `robot_url`:
    the robot listening (udpin/tcpin) -> the GCS sends there (udpout/tcp); the
    robot sending (udpout/udp) -> the GCS listens (udpin)."""
    scheme, sep, rest = robot_url.partition(":")
    if not sep:
        return robot_url  # a serial device: the other end of the line
    return {"udpin": f"udpout:{rest}", "tcpin": f"tcp:{rest}", "udpout": f"udpin:{rest}",
            "udp": f"udpin:{rest}", "tcp": f"tcpin:{rest}"}.get(scheme, robot_url)


def validate(opts: SitlOptions) -> None:
    if not (opts.speed > 0 and math.isfinite(opts.speed)):
        raise SitlError(f"--speed must be a positive number, got {opts.speed:g}")
    if opts.can is not None and opts.can.startswith("virtual"):
        raise SitlError(f"--can {opts.can}: a virtual bus does not reach another process; leave --can out "
                        "for a hub")
    if opts.duration_s is not None and not opts.duration_s > 0:
        raise SitlError(f"--duration must be positive, got {opts.duration_s:g}")
    problem = check_url(opts.mavlink)  # the check every MAVLink command's --mavlink gets
    if problem is not None:
        raise SitlError(f"--mavlink {opts.mavlink}: expected a MAVLink connection string ({problem})")
    if opts.profile is not None:
        from firmware_py.profile import ProfileError, load_profile

        try:
            load_profile(opts.profile)
        except ProfileError as exc:
            raise SitlError(f"--profile {exc}") from None


def port_in_use(url: str) -> str | None:
    """None when the port a listening robot (udpin:/tcpin:HOST:PORT) would bind is free, else the
    one-line reason. pymavlink binds with SO_REUSEADDR, so two robots could share a port (each GCS
    frame reaching one of them); a probe bind without it fails while anything holds the port."""
    import socket

    scheme, _, rest = url.partition(":")
    if scheme not in ("udpin", "tcpin"):
        return None
    host, _, port = rest.rpartition(":")
    kind, name = (socket.SOCK_DGRAM, "UDP") if scheme == "udpin" else (socket.SOCK_STREAM, "TCP")
    try:
        with socket.socket(socket.AF_INET, kind) as probe:
            if kind == socket.SOCK_STREAM:  # a TIME_WAIT left by an earlier run is not a listener
                probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind((host, int(port)))
    except OSError as exc:
        why = "in use (another qnav sitl or robot?)" if exc.errno == errno.EADDRINUSE else (exc.strerror or str(exc))
        return f"{name} port {port} on {host}: {why}; give another port, e.g. --mavlink {scheme}:{host}:{int(port) + 1}"
    return None


def describe_exits(codes: dict[str, int | None]) -> str:
    """The children's ends for the last line: "sim exit 0, robot interrupted (SIGINT)". A negative
    Popen status is the signal that ended the child (an early Ctrl-C, before its own handler)."""
    import signal

    def one(code: int | None) -> str:
        if code is None:
            return "not started"
        if code >= 0:
            return f"exit {code}"
        try:
            sig = signal.Signals(-code).name
        except ValueError:
            sig = f"signal {-code}"
        return f"interrupted ({sig})" if sig in ("SIGINT", "SIGTERM") else f"killed ({sig})"

    return ", ".join(f"{name} {one(code)}" for name, code in codes.items()) or "none started"


def connection_help(info: SitlInfo) -> list[str]:
    """The lines `qnav sitl` prints once the robot is up."""
    gcs = info.gcs_url
    dbc = Path(__file__).resolve().parents[1] / "firmware_py" / "qnav.dbc"
    lines = [
        f"robot sysid {info.sysid if info.sysid is not None else '?'} up; its MAVLink: {info.mavlink}",
        "connect a ground station:",
        f"  MAVProxy        mavproxy.py --master={gcs}   (add --out udp:127.0.0.1:14550 to feed QGroundControl)",
    ]
    scheme, _, rest = gcs.partition(":")
    if scheme == "udpout":
        lines.append(f"  QGroundControl  Comm Links > Add > UDP, target host {rest} (or via MAVProxy --out above)")
    elif scheme == "udpin" and rest.endswith(":14550"):
        lines.append("  QGroundControl  connects by itself (it listens on UDP 14550)")
    elif scheme == "tcp":
        lines.append(f"  QGroundControl  Comm Links > Add > TCP, {rest}")
    lines += [f"  MAVSDK          System(sysid=255).connect(system_address=\"{_mavsdk_address(gcs)}\")",
              f"  qnav            qnav monitor --mavlink {gcs}   (also qnav upload/mission/arm/mode/goal)",
              f"CAN bus: {info.can_spec}" + (" (python-can-remote hub)" if info.hub else "")]
    # qnav.dbc decodes qnav's own frames only: with an ODrive (CANSimple) or DroneCAN backend the bus
    # carries frames it does not describe, and a decoder over qnav.dbc would show them as unknown
    protocols = {"odrive": "ODrive CANSimple", "dronecan": "DroneCAN"}
    foreign = [f"{what} ({protocols.get(backend, backend)})" for what, backend
               in (("drive", info.drive_backend), ("sensors", info.sensor_backend)) if backend != "qnav"]
    if info.can_spec.startswith("socketcan:"):
        channel = info.can_spec.partition(":")[2]
        lines.append(f"  candump -L {channel}      cansniffer -c {channel}")
        if not foreign:
            lines.append(f"  cantools monitor -i socketcan -c {channel} {dbc}")
    elif info.can_spec.startswith("remote:"):
        url = info.can_spec.partition(":")[2]
        if not foreign:
            lines.append(f"  cantools monitor -i remote -c {url} {dbc}")
        lines.append(f"  python -m can.viewer -i remote -c {url}")
    if foreign:
        lines.append(f"  the profile's {' and '.join(foreign)} frames are not in qnav.dbc: no cantools decoder "
                     "here; the tools above show every frame raw")
    lines += [f"run folder {info.run_dir} (sim.log, robot.log"
              + (", mavlink.tlog" if "tlog" in info.logs else "") + "; can.blf, trajectory.csv and run.mcap when stopped)",
              "Ctrl-C stops every process"]
    return lines


def _mavsdk_address(gcs_url: str) -> str:
    scheme, _, rest = gcs_url.partition(":")
    host, _, port = rest.rpartition(":")
    mavsdk = {"udpout": "udpout", "udpin": "udpin", "tcp": "tcpout"}.get(scheme)
    return f"{mavsdk}://{host}:{port}" if mavsdk else gcs_url


def load_world(map_name: str):  # type: ignore[no-untyped-def]
    """The map the sim runs (SitlError naming it if it cannot be loaded)."""
    from ground_station.maps import MapError, load_map

    try:
        return load_map(map_name)
    except (MapError, OSError, ValueError) as exc:
        raise SitlError(f"--map {map_name}: {exc}") from None


def start_pose(grid_map) -> tuple[str, tuple[int, int]]:  # type: ignore[no-untyped-def]
    """The sim's default start (the free cell nearest the map centre, heading east)
    as a --start value, given to both programs so the robot's odometry starts true."""
    col, row = start_cell(grid_map.occ)
    x, y = grid_map.cell_size_m * (col + 0.5), grid_map.cell_size_m * (grid_map.height - row - 0.5)
    return f"{x:g},{y:g},0", (col, row)


def resolve_policy(opts: SitlOptions) -> str:
    spec = opts.policy or SHIPPED_FOR_MAP.get(Path(opts.map_name).stem if opts.map_name.endswith(".map")
                                              else opts.map_name, FALLBACK_POLICY)
    if spec == "none":
        return ""
    try:
        path = resolve_policy_spec(spec)
    except ShippedPolicyError as exc:
        raise SitlError(f"--policy {spec}: {exc}") from None
    if not Path(path).is_file():
        raise SitlError(f"--policy {spec}: no such file")
    return str(path)


class Sitl:
    """The running bring-up; `start()`, then `wait()`, `stop()` always."""

    def __init__(self, opts: SitlOptions, say: Callable[[str], None] | None = None) -> None:
        validate(opts)
        self.opts = opts
        self.say = say or (lambda _line: None)
        self.procs = ProcessGroup()
        self.hub: CanHub | None = None
        self.relay: TlogRelay | None = None
        self.info: SitlInfo | None = None
        self.exit_codes: dict[str, int | None] = {}

    def start(self) -> SitlInfo:
        opts = self.opts
        world = load_world(opts.map_name)
        start, cell = start_pose(world)
        policy = resolve_policy(opts)
        busy = port_in_use(opts.mavlink)  # before anything starts (no hub, no run folder): one robot per port
        if busy is not None:
            raise SitlError(f"--mavlink {opts.mavlink}: {busy}")
        run_dir = Path(opts.out) if opts.out else default_run_dir("sitl")
        try:
            (run_dir / "robot").mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SitlError(f"run folder {run_dir}: {exc.strerror or exc}") from None
        can_spec = opts.can
        if can_spec is None:
            hub = self.hub = CanHub(channel="qnav-sitl")
            try:
                hub.start()
            except RuntimeError as exc:
                raise SitlError(f"CAN hub: {exc}") from None
            can_spec = hub.spec
        logs = {"sim": run_dir / "sim.log", "robot": run_dir / "robot.log"}
        robot_mavlink = opts.mavlink
        if relayable(opts.mavlink):  # the run's own telemetry record (module docstring)
            try:
                self.relay = TlogRelay(opts.mavlink, run_dir / "mavlink.tlog")
            except OSError as exc:
                raise SitlError(f"--mavlink {opts.mavlink}: {exc.strerror or exc}") from None
            robot_mavlink = self.relay.robot_url()
            logs["tlog"] = self.relay.tlog_path
        info = SitlInfo(run_dir=run_dir, mavlink=opts.mavlink, gcs_url=gcs_side(opts.mavlink), can_spec=can_spec,
                        hub=self.hub is not None, policy=policy or "none", start=start, logs=logs)
        if opts.profile is not None:
            from firmware_py.profile import load_profile

            profile = load_profile(opts.profile)  # validate() has checked it
            info.drive_backend, info.sensor_backend = profile.drive.backend, profile.sensors.backend
        self.info = info
        pace = ["--lockstep", "--max-speed", f"{opts.speed:g}"] if opts.lockstep else ["--speed", f"{opts.speed:g}"]
        sim_argv = qnav_sim("--map", opts.map_name, "--can", can_spec, *pace,
                            "--start", start, "--seed", str(opts.seed), "--duration", str(SIM_DURATION_S),
                            "--log", run_dir / "can.blf", "--trajectory", run_dir / "trajectory.csv", "-q",
                            *(["--profile", str(opts.profile)] if opts.profile is not None else []),
                            die_with_parent=True)
        # the robot knows the world it is in (a policy for another map is refused): the map is in its
        # storage as `qnav map upload` leaves it, served to ground stations over MAVLink FTP
        from firmware_py.atomic import atomic_write
        from firmware_py.storage import ACTIVE_MAP
        from ground_station.maps import write_map
        from ground_station.mavlink.robot_map import MAP_TARGETS, targets_file

        write_map(run_dir / "map.map", world)
        map_text = (run_dir / "map.map").read_bytes()
        atomic_write(run_dir / "robot" / ACTIVE_MAP.lstrip("/"), map_text, make_parents=True)
        name = Path(opts.map_name).stem if opts.map_name.endswith(".map") else opts.map_name
        atomic_write(run_dir / "robot" / MAP_TARGETS.lstrip("/"), targets_file(map_text, name, world.targets))
        robot_argv = qnav_robot("--can", can_spec, "--lockstep" if opts.lockstep else "--sim-clock", "--start", start,
                                "--map", run_dir / "robot" / ACTIVE_MAP.lstrip("/"),  # a refusal ends it loudly
                                "--cell-size", f"{world.cell_size_m:g}",
                                "--storage", run_dir / "robot",
                                "--mavlink", robot_mavlink, "--mavlink-autopilot", opts.autopilot,
                                "--stats-json", run_dir / "robot_stats.json",
                                *(["--profile", str(opts.profile)] if opts.profile is not None else []),
                                die_with_parent=True)
        if policy:  # the robot boots it from its storage, as a real robot does: its FTP server then
            # has it as /policies/active.qtab, where `qnav mission upload --targets` reads the robot's map
            from firmware_py.storage import ACTIVE_POLICY

            active = run_dir / "robot" / ACTIVE_POLICY.lstrip("/")
            active.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(active, Path(policy).read_bytes())
        self.procs.start("sim", sim_argv, logs["sim"])
        self.procs.start("robot", robot_argv, logs["robot"])
        pace_text = f"lockstep, at most x{opts.speed:g}" if opts.lockstep else f"x{opts.speed:g} real time"
        self.say(f"qnav-sim (map {opts.map_name}, {pace_text}) and qnav-robot "
                 f"(policy {info.policy}) started at cell {cell}, start {start}")
        info.sysid = self._probe(info)
        return info

    def _probe(self, info: SitlInfo) -> int | None:
        """Wait for the robot's HEARTBEAT past BOOT (its first control tick: before it an arm is
        refused "still booting"), only when it listens: a robot sending to a fixed address is
        heard by the GCS there, not by us."""
        if not info.mavlink.startswith(("udpin:", "tcpin:")):
            return None
        import os

        os.environ.setdefault("MAVLINK20", "1")
        from pymavlink import mavutil

        deadline = time.monotonic() + self.opts.probe_timeout_s
        conn = None
        try:
            while conn is None:
                try:
                    # as the operator's system (SYSID_MYGCS, 255): the robot takes PARAM_SET from it only; another
                    # component id, and an onboard-controller heartbeat, so it is no GCS for the failsafe
                    conn = mavutil.mavlink_connection(info.gcs_url, source_system=255, source_component=191)
                except OSError:  # tcpin not listening yet
                    self._check_children()
                    if time.monotonic() > deadline:
                        raise SitlError(f"robot's {info.mavlink} never accepted a connection") from None
                    time.sleep(0.2)
            M = mavutil.mavlink
            booting = False
            while time.monotonic() < deadline:
                self._check_children()
                conn.mav.heartbeat_send(M.MAV_TYPE_ONBOARD_CONTROLLER, M.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                msg = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
                if msg is None or msg.get_srcSystem() == 255:
                    continue
                if msg.system_status == M.MAV_STATE_BOOT:
                    booting = True  # up before its first control tick: it would refuse to arm yet
                    continue
                sysid = msg.get_srcSystem()
                if self.opts.speed > 1:
                    for param in SPEED_SCALED_PARAMS:
                        self._scale_timeout(conn, sysid, msg.get_srcComponent(), param.name,
                                            min(param.max, math.ceil(param.default * self.opts.speed)))
                return int(sysid)
            if booting:
                raise SitlError(f"the robot on {info.mavlink} was still booting (no control tick) after "
                                f"{self.opts.probe_timeout_s:g} s (see {info.logs['robot']}, {info.logs['sim']})")
            raise SitlError(f"no HEARTBEAT from the robot on {info.mavlink} within "
                            f"{self.opts.probe_timeout_s:g} s (see {info.logs['robot']})")
        finally:
            if conn is not None:
                conn.close()

    def _scale_timeout(self, conn, sysid: int, compid: int, name: str, value: int) -> None:
        for _attempt in range(5):
            conn.mav.param_set_send(sysid, compid, name.encode(), float(value), 6)  # MAV_PARAM_TYPE_INT32
            msg = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=1.0)
            if msg is not None and msg.param_id == name:
                self.say(f"{name} set to {round(msg.param_value)} ms (robot time runs x{self.opts.speed:g})")
                return
        self.say(f"warning: could not raise {name}; a ground station may time out at this speed")

    def _check_children(self) -> None:
        dead = self.procs.dead()
        if dead:
            name, code = dead[0]
            child = dict(self.procs.children)[name]
            raise SitlError(f"{name} exited with status {code}: {child.log_tail(3)}")

    def wait(self, poll_s: float = 0.25) -> WaitResult:
        """Until a child ends (child_died, "<name> exited ..."), `duration_s` passes
        ("duration reached") or KeyboardInterrupt (raised through)."""
        deadline = None if self.opts.duration_s is None else time.monotonic() + self.opts.duration_s
        while True:
            try:
                self._check_children()
            except SitlError as exc:
                return WaitResult(str(exc), child_died=True)
            if deadline is not None and time.monotonic() >= deadline:
                return WaitResult("duration reached", child_died=False)
            time.sleep(poll_s)

    def stop(self) -> dict[str, int | None]:
        if self.procs.children:
            self.say("stopping the sim and the robot" + (", then writing run.mcap" if self.info is not None else ""))
        try:
            self.exit_codes = self.procs.stop_all()
        finally:
            if self.relay is not None:  # after the robot: its last frames are in the tlog
                self.relay.close()
                self.relay = None
            if self.hub is not None:
                self.hub.stop()
                self.hub = None
        if self.info is not None:
            self._write_mcap(self.info.run_dir)
        return self.exit_codes

    def _write_mcap(self, run_dir: Path) -> None:
        """run.mcap of the whole run (tlog, CAN log, ground truth, robot.log, map), as `qnav log mcap
        RUN_DIR` makes it; a progress line each second while it is written."""
        can_log, traj, tlog = run_dir / "can.blf", run_dir / "trajectory.csv", run_dir / "mavlink.tlog"
        tlog_ok = tlog.is_file() and tlog.stat().st_size > 0
        if not can_log.is_file() and not tlog_ok:
            return
        from ground_station.logs.mcap_run import write_run_mcap
        from ground_station.maps import load_map

        robot_log = run_dir / "robot.log"
        inputs = [p for p in (tlog if tlog_ok else None, can_log, traj, robot_log) if p is not None and p.is_file()]
        size_mb = sum(p.stat().st_size for p in inputs) / 1e6
        self.say(f"writing {run_dir / 'run.mcap'} from {', '.join(p.name for p in inputs)} ({size_mb:.1f} MB): 0%")
        last = [time.monotonic()]

        def progress(frac: float) -> None:
            now = time.monotonic()
            if now - last[0] >= PROGRESS_PERIOD_S and frac < 1.0:
                last[0] = now
                self.say(f"writing run.mcap: {frac:.0%}")

        started = time.monotonic()
        try:
            s = write_run_mcap(run_dir / "run.mcap", tlog if tlog_ok else None,
                               can_log=can_log if can_log.is_file() else None,
                               trajectory=traj if traj.is_file() else None, grid_map=load_map(self.opts.map_name),
                               robot_log=robot_log if robot_log.is_file() else None, progress=progress)
        except Exception as exc:  # noqa: BLE001 - the bring-up's clean-up says it and goes on
            self.say(f"run.mcap not written: {type(exc).__name__}: {exc}")
            return
        what = ("telemetry (mavlink.tlog), " if tlog_ok else "no telemetry (the robot's MAVLink is not UDP), ")
        self.say(f"wrote {run_dir / 'run.mcap'} in {time.monotonic() - started:.1f} s: {what}CAN, ground truth, "
                 f"map, robot log; {len(s.messages)} topics (open it in Foxglove)")
