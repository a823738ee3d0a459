"""The textual dashboard of `qnav monitor`.

Shape (as cantools' monitor): a timer polls the message source without blocking ->
`VehicleView.update` -> panels are redrawn only when the view changed (or once a second, for the
heartbeat age). Everything shown is a pure function of the view (`render_*` below), so tests can
check the text without a terminal and textual's pilot can check the live widgets.

Keys: a arm, d disarm, h hold (COMMAND_LONG to the robot), q quit.
"""

from __future__ import annotations

import math

from rich.text import Text
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.timer import Timer
from textual.widgets import Footer, Header, Static

from firmware_py import robot_spec
from ground_station.monitor.model import VehicleView, policy_id_text
from ground_station.monitor.sources import MessageSource

_ARROWS = "→↗↑↖←↙↓↘"  # heading CCW from east, 45° steps
_POLL_S = 0.05


def heading_arrow(heading: float) -> str:
    return _ARROWS[int(round(heading / (math.pi / 4))) % 8]


def _cell_of(x: float, y: float, height: int, cell_m: float) -> tuple[int, int]:
    cell_mm = int(round(cell_m * 1000))
    return robot_spec.world_to_cell(int(math.floor(x * 1000)), int(math.floor(y * 1000)), height, cell_mm)


def render_map(view: VehicleView, grid_map=None) -> Text:
    """The map, north up, two characters per cell: obstacles, trail, targets (letters), the current
    goal (◎, or its letter highlighted) and the robot (an arrow along its heading)."""
    if grid_map is not None:
        occ = grid_map.occ
        height, width = occ.shape
        cell_m = grid_map.cell_size_m
        targets = {pos: name for name, pos in grid_map.targets.items()}
    else:  # no map: a blank field around what we know, 0.5 m cells
        occ, cell_m, targets = None, robot_spec.DEFAULT_CELL_SIZE_MM / 1000, {}
        xs = [p[0] for p in view.trail] + ([view.x] if view.x is not None else [])
        ys = [p[1] for p in view.trail] + ([view.y] if view.y is not None else [])
        width = max(10, int(math.ceil(max(xs, default=0) / cell_m)) + 1)
        height = max(10, int(math.ceil(max(ys, default=0) / cell_m)) + 1)

    trail = {_cell_of(x, y, height, cell_m) for x, y in view.trail}
    mission = {_cell_of(x, y, height, cell_m) for x, y in view.mission.items.values()}
    goal = view.goal_estimate()
    goal_cell = _cell_of(*goal, height, cell_m) if goal is not None else None
    robot_cell = _cell_of(view.x, view.y, height, cell_m) if view.x is not None and view.y is not None else None

    out = Text()
    for row in range(height):
        for col in range(width):
            c = (col, row)
            if c == robot_cell:
                out.append(heading_arrow(view.heading or 0.0) + " ", style="bold bright_green")
            elif c in targets:
                style = "bold black on yellow" if c == goal_cell else "bold yellow"
                out.append(f"{targets[c]:<2}", style=style)
            elif c == goal_cell:
                out.append("◎ ", style="bold yellow")
            elif c in mission:
                out.append("○ ", style="yellow")
            elif occ is not None and occ[row, col]:
                out.append("██", style="grey50")
            elif c in trail:
                out.append("• ", style="cyan")
            else:
                out.append("· ", style="grey35")
        out.append("\n")
    if robot_cell is not None and not (0 <= robot_cell[0] < width and 0 <= robot_cell[1] < height):
        out.append(f"robot off the map at x={view.x:.2f} y={view.y:.2f} m\n", style="bold red")
    return out


def render_link(view: VehicleView, now: float) -> Text:
    age = view.heartbeat_age(now)
    link = view.link
    t = Text()
    if age is None:
        t.append("no heartbeat yet\n", style="bold red")
    else:
        style = "green" if age < 2 else ("yellow" if age < 5 else "bold red")
        t.append(f"heartbeat age {age:5.1f} s\n", style=style)
    t.append(f"packets {link.received}  lost {link.lost} ({link.loss_pct:.1f}%)\n")
    sig = "signed" if link.signing else "unsigned"
    if link.verified_frames:
        sig += f", {link.verified_frames} verified"
    t.append(f"signing {sig}\n", style="green" if link.signing else "yellow")
    t.append(f"robot rx drops {link.rx_dropped} ({link.drop_rate_comm_pct:.2f}%)\n")
    t.append(f"signing drops {link.signing_dropped}  CAN errors {link.can_errors}")
    return t


def render_vehicle(view: VehicleView) -> Text:
    t = Text()
    t.append(f"mode {view.mode_name}  ", style="bold")
    t.append("ARMED" if view.armed else "disarmed", style="bold red" if view.armed else "green")
    t.append("\n")
    t.append(f"controller {view.ctrl_name}\n", style="bold red" if view.ctrl_name == "FAULT" else "")
    if view.failsafe:
        t.append("FAILSAFE (system status CRITICAL)\n", style="bold white on red")
    t.append(f"policy id {policy_id_text(view.policy_id)}\n")
    pose = view.pose
    if pose is None:
        t.append("pose -")
    else:
        t.append(f"pose x {pose[0]:.2f} y {pose[1]:.2f} m  hdg {round(math.degrees(pose[2]))}°\n"
                 f"speed {view.speed:.2f} m/s")
    if view.localised is not None:
        t.append("\n" + view.localisation_text.replace("localised=no", "NOT LOCALISED"),
                 style="" if view.localised else "bold yellow")
    if view.load_pct is not None:
        t.append(f"\nload {view.load_pct:.1f}%")
        t.append(f"  tick overruns {view.link.tick_overruns}")
    return t


def render_policy(view: VehicleView) -> Text:
    t = Text()
    t.append(f"state {view.state_index if view.state_index is not None else '-'}  "
             f"action {view.action if view.action is not None and view.action >= 0 else '-'}\n")
    if not view.q_row:
        t.append("Q-row -")
        return t
    idx = sorted(view.q_row)
    best = max(idx, key=lambda i: (view.q_row[i], -i))  # ties -> lowest index, as kinds.base.best_action
    t.append("Q-row ")
    for i in idx:
        t.append(f"[{i}]{view.q_row[i]} ", style="bold green" if i == best else "")
    return t


def render_sectors(view: VehicleView) -> Text:
    t = Text()
    if not view.sectors:
        t.append("no OBSTACLE_DISTANCE yet")
        return t
    rmax = view.sector_max_m or 2.0
    for angle, rng in sorted(view.sectors, key=lambda s: -s[0]):
        deg = int(round(math.degrees(angle)))
        if rng is None:
            t.append(f"{deg:+5d}° clear (> {rmax:.1f} m)\n", style="grey50")
            continue
        n = int(round(10 * min(rng, rmax) / rmax))
        style = "red" if rng < 0.3 else ("yellow" if rng < 0.6 else "green")
        t.append(f"{deg:+5d}° {rng:4.2f} ")
        t.append("█" * n + "░" * (10 - n) + "\n", style=style)
    t.rstrip()
    return t


def render_mission(view: VehicleView, grid_map=None) -> Text:
    m = view.mission
    t = Text()
    if m.total == 0 and m.current < 0:
        t.append("no mission")
    else:
        t.append(f"item {view.mission_progress}  reached {view.mission_reached_count}"
                 + (f" ({', '.join(str(s) for s in m.reached)})" if m.reached else ""))
    d = view.distance_to_goal()
    goal = view.goal_estimate()
    if goal is not None:
        label = ""
        if grid_map is not None:
            cell = _cell_of(*goal, grid_map.height, grid_map.cell_size_m)
            label = next((f" ({n})" for n, pos in grid_map.targets.items() if pos == cell), "")
        kind = "" if view.goal is not None else " ~"
        t.append(f"\ngoal{kind} x {goal[0]:.2f} y {goal[1]:.2f}{label}")
    if d is not None:
        t.append(f"  distance {d:.2f} m")
    return t


def render_log(view: VehicleView, lines: int = 8) -> Text:
    t = Text()
    t0 = view.t0 or 0.0
    for entry in list(view.log)[-lines:]:
        style = "bold red" if entry.severity <= 3 else ("yellow" if entry.severity == 4 else "")
        # the robot's clock (sim time in HIL) when it has sent one, else receive time
        when = entry.robot_t if entry.robot_t is not None else entry.t - t0
        t.append(f"{when:7.1f}s {entry.severity_name:<6} {entry.text}\n", style=style)
    t.rstrip()
    return t


class MonitorApp(App):
    """Live (or replayed) telemetry dashboard."""

    TITLE = "qnav monitor"
    CSS = """
    #top { height: 1fr; }
    #map { width: auto; min-width: 24; height: auto; border: round $accent; padding: 0 1; }
    .column { width: 1fr; height: auto; }
    .panel { border: round $primary; height: auto; padding: 0 1; }
    #log { border: round $primary; height: 10; padding: 0 1; }
    """
    BINDINGS = [
        Binding("a", "command('arm')", "arm"),
        Binding("d", "command('disarm')", "disarm"),
        Binding("h", "command('hold')", "hold"),
        Binding("q", "quit", "quit"),
    ]

    def __init__(self, source: MessageSource, grid_map=None, view: VehicleView | None = None,
                 subtitle: str = "") -> None:
        super().__init__()
        self.source = source
        self.grid_map = grid_map
        self.view = view if view is not None else VehicleView()
        self._drawn_version = -1
        self._drawn_second = -1
        self._panels: dict[str, Static] = {}
        self._timer: Timer | None = None
        self._map_version = 0
        self.sub_title = subtitle

    def compose(self) -> ComposeResult:
        yield Header()
        with Horizontal(id="top"):
            yield Static(id="map")
            for column in (("link", "vehicle", "policy"), ("sectors", "mission")):
                with Vertical(classes="column"):
                    for name in column:
                        panel = Static(id=name, classes="panel")
                        panel.border_title = name
                        yield panel
        log = Static(id="log")
        log.border_title = "log"
        yield log
        yield Footer()

    def on_mount(self) -> None:
        self._panels = {w.id: w for w in self.query(Static) if w.id}
        self._map_version = getattr(self.source, "map_version", 0)
        self._title_map()
        self._timer = self.set_interval(_POLL_S, self.pump)
        self.redraw()

    def _title_map(self) -> None:
        title = self.grid_map.name if self.grid_map is not None else "map"
        self._panels["map"].border_title = title
        # the panel is as wide as the map's cells; a longer name would be cut on the border
        self._panels["map"].styles.min_width = max(24, len(title) + 8)

    def pump(self) -> None:
        """Drain the source into the view; redraw if anything changed."""
        for msg, t in self.source.poll():
            self.view.update(msg, t)
        version = getattr(self.source, "map_version", 0)
        if version != self._map_version:  # the robot's own map, read or changed (RobotMapSource)
            self._map_version = version
            self.grid_map = getattr(self.source, "grid_map", None)
            self._title_map()
            self.redraw()
        second = int(self.source.now())
        if self.view.version != self._drawn_version or second != self._drawn_second:
            self.redraw()
        if self.source.finished and "replay finished" not in self.sub_title:
            self.sub_title = (self.sub_title + "  (replay finished)").strip()

    def redraw(self) -> None:
        v, now = self.view, self.source.now()
        self._drawn_version, self._drawn_second = v.version, int(now)
        p = self._panels
        p["map"].update(render_map(v, self.grid_map))
        p["link"].update(render_link(v, now))
        p["vehicle"].update(render_vehicle(v))
        p["policy"].update(render_policy(v))
        p["sectors"].update(render_sectors(v))
        p["mission"].update(render_mission(v, self.grid_map))
        p["log"].update(render_log(v))

    def action_command(self, kind: str) -> None:
        target = (self.view.sysid or 1, self.view.compid or 1)
        note = self.source.send_command(kind, target)
        self.notify(note, timeout=3)

    def on_unmount(self) -> None:
        if self._timer is not None:
            self._timer.stop()
