"""Post-run report from a .tlog: summary JSON and PNG plots.

`analyse(path)` replays the recording through the same `VehicleView` the monitor uses and samples it
into a `RunRecord`; `write_report(record, out, grid_map)` writes `summary.json` and the plots
(trajectory, distance to goal, actions, timing). A plot whose data the recording does not hold is
not drawn; the JSON says which and why under `plots_skipped` (nothing is faked). Times are on the
robot's own clock when the recording has it, else on the tlog's receive stamps (`clock` in the
JSON); one vehicle is followed, what was ignored is counted under `ignored`. The plots, the clock
and the definitions of goals reached, stops and faults: docs/monitor.md, `qnav report`.
"""

from __future__ import annotations

import datetime
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from firmware_py import robot_spec
from firmware_py.atomic import atomic_write
from firmware_py.vehicle import CtrlState, Mode
from ground_station.monitor.model import NV_ACTION, VehicleView, field_text

STOP_SPEED_M_S = 0.02
STOP_YAW_RATE = 0.05
STOP_MIN_S = 1.0
EPISODE_GAP_S = 1.0
GOAL_DEDUP_S = 1.0


@dataclass
class RunRecord:
    """Samples and events of one recording (times in seconds from its start)."""

    path: str
    clock: str = "robot"  # "robot": time_boot_ms (sim time in HIL); "wall": tlog receive stamps
    wall_s: float = 0.0  # the recording's span in receive (wall) time
    messages: int = 0
    t0: float | None = None
    t_end: float = 0.0
    pose: list[tuple[float, float, float, float, float]] = field(default_factory=list)  # t, x, y, speed, yaw rate
    driving: list[bool] = field(default_factory=list)  # per pose sample: armed, Auto/Guided, DRIVING
    distance: list[tuple[float, float]] = field(default_factory=list)  # t, metres to goal
    actions: list[int] = field(default_factory=list)
    load_pct: list[tuple[float, float]] = field(default_factory=list)
    overruns: list[tuple[float, int]] = field(default_factory=list)  # cumulative tick overruns
    mission_reached: list[tuple[float, int]] = field(default_factory=list)
    goal_state_entries: list[float] = field(default_factory=list)
    fault_events: list[tuple[float, str]] = field(default_factory=list)
    first_armed: float | None = None
    first_driving: float | None = None  # armed and the controller DRIVING: the mission under way
    view: VehicleView = field(default_factory=VehicleView)


CLOCK_NAMES = {"robot": "robot time_boot_ms (sim time in HIL)", "wall": "tlog receive time (wall clock)"}


def analyse(path: str | os.PathLike[str], progress: bool = False, sysid: int | None = None,
            clock: str = "auto") -> RunRecord:
    """Replay a .tlog through a VehicleView and collect what the report needs.

    `clock`: "robot" (the vehicle's time_boot_ms), "wall" (tlog stamps) or
    "auto" (robot when the recording carries it, else wall)."""
    if clock == "auto":
        rec = _analyse(str(path), progress, sysid, "robot")
        if rec.view.robot_s is not None:
            return rec
        clock = "wall"
    return _analyse(str(path), progress, sysid, clock)


def _robot_wall_clock(unix_us: int | None) -> str | None:
    if unix_us is None:
        return None  # the robot sent no SYSTEM_TIME
    if unix_us == 0:
        return "unset"
    return datetime.datetime.fromtimestamp(unix_us / 1e6, tz=datetime.UTC).isoformat(timespec="seconds")


def _analyse(path: str, progress: bool, sysid: int | None, clock: str) -> RunRecord:
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil
    from tqdm import tqdm

    rec = RunRecord(path=path, clock=clock, view=VehicleView(sysid=sysid))
    view = rec.view
    log = mavutil.mavlogfile(path, robust_parsing=True)
    size = os.path.getsize(path)
    bar = tqdm(total=size, unit="B", unit_scale=True, desc="reading tlog", disable=not progress or None)
    prev_ctrl, prev_failsafe = None, False
    try:
        while True:
            msg = log.recv_msg()
            if msg is None:
                break
            bar.update(log.f.tell() - bar.n)
            if msg.get_type() == "BAD_DATA":
                continue
            t_abs = msg._timestamp
            log_before = view.log_total
            if not view.update(msg, t_abs):
                continue
            rec.messages += 1
            if rec.t0 is None:
                rec.t0 = t_abs
            if clock == "robot":
                t = view.robot_clock(t_abs) or 0.0  # messages before the first timed one: its start
            else:
                t = t_abs - rec.t0
            rec.t_end = max(rec.t_end, t)
            rec.wall_s = t_abs - rec.t0
            mtype = msg.get_type()
            if view.armed and rec.first_armed is None:
                rec.first_armed = t
            if view.armed and view.ctrl_state == CtrlState.DRIVING and rec.first_driving is None:
                rec.first_driving = t
            if mtype == "LOCAL_POSITION_NED":
                assert view.x is not None and view.y is not None  # set by this very message
                rec.pose.append((t, view.x, view.y, view.speed, view.yaw_rate))
                rec.driving.append(view.armed and view.mode in (Mode.AUTO, Mode.GUIDED)
                                   and view.ctrl_state in (None, CtrlState.DRIVING))
                d = view.distance_to_goal()
                if d is not None and view.armed:
                    rec.distance.append((t, d))
            elif mtype == "NAMED_VALUE_INT":
                if field_text(msg.name) == NV_ACTION and msg.value >= 0:
                    rec.actions.append(msg.value)
            elif mtype == "SYS_STATUS":
                assert view.load_pct is not None  # set by this very message
                rec.load_pct.append((t, view.load_pct))
                rec.overruns.append((t, view.link.tick_overruns))
            elif mtype == "MISSION_ITEM_REACHED":
                rec.mission_reached.append((t, msg.seq))
            _fault_texts(rec, view, log_before, t)  # a text may complete on any frame (its last chunk lost)
            if view.ctrl_state != prev_ctrl:
                if view.ctrl_state == CtrlState.GOAL_REACHED:
                    rec.goal_state_entries.append(t)
                elif view.ctrl_state == CtrlState.FAULT:
                    rec.fault_events.append((t, "controller entered FAULT"))
                prev_ctrl = view.ctrl_state
            if view.failsafe and not prev_failsafe:
                rec.fault_events.append((t, "failsafe (system status CRITICAL)"))
            prev_failsafe = view.failsafe
        log_before = view.log_total
        view.flush_texts()  # texts still waiting for a chunk when the recording ends
        _fault_texts(rec, view, log_before, rec.t_end)
    finally:
        bar.close()
        log.close()
    return rec


def _fault_texts(rec: RunRecord, view: VehicleView, log_before: int, t: float) -> None:
    """The error-or-worse STATUSTEXTs (severity <= 3) the view logged since `log_before`."""
    new = min(view.log_total - log_before, len(view.log))
    for line in list(view.log)[len(view.log) - new:] if new else []:
        if line.severity <= 3:  # ACK lines are INFO or WARNING
            rec.fault_events.append((t, f"{line.severity_name}: {line.text}"))


def _stops(rec: RunRecord) -> list[dict]:
    stops, start = [], None
    for (t, _x, _y, v, w), driving in zip(rec.pose, rec.driving, strict=True):
        still = driving and v < STOP_SPEED_M_S and abs(w) < STOP_YAW_RATE
        if still and start is None:
            start = t
        elif not still and start is not None:
            if t - start >= STOP_MIN_S:
                stops.append({"t_s": round(start, 3), "duration_s": round(t - start, 3)})
            start = None
    if start is not None and rec.pose and rec.pose[-1][0] - start >= STOP_MIN_S:
        stops.append({"t_s": round(start, 3), "duration_s": round(rec.pose[-1][0] - start, 3)})
    return stops


def _episodes(events: list[tuple[float, str]]) -> list[dict]:
    episodes: list[dict] = []
    for t, what in sorted(events):
        if episodes and t - episodes[-1]["t_end"] < EPISODE_GAP_S:
            episodes[-1]["t_end"] = t
            if what not in episodes[-1]["events"]:
                episodes[-1]["events"].append(what)
        else:
            episodes.append({"t_s": t, "t_end": t, "events": [what]})
    return [{"t_s": round(e["t_s"], 3), "events": e["events"]} for e in episodes]


def _target_name(xy: tuple[float, float], grid_map) -> str | None:
    if grid_map is None:
        return None
    cell_mm = int(round(grid_map.cell_size_m * 1000))
    cell = robot_spec.world_to_cell(int(math.floor(xy[0] * 1000)), int(math.floor(xy[1] * 1000)), grid_map.height, cell_mm)
    return next((n for n, pos in grid_map.targets.items() if pos == cell), None)


def summarise(rec: RunRecord, grid_map=None) -> dict:
    """The summary JSON (without plot paths)."""
    view = rec.view
    reached_t = [t for t, _ in rec.mission_reached]
    guided = [t for t in rec.goal_state_entries if all(abs(t - r) > GOAL_DEDUP_S for r in reached_t)]
    goal_times = sorted(reached_t + guided)
    path_len = sum(math.hypot(b[1] - a[1], b[2] - a[2]) for a, b in zip(rec.pose, rec.pose[1:], strict=False))
    reached_items = []
    for t, seq in rec.mission_reached:
        item: dict[str, object] = {"t_s": round(t, 3), "seq": seq}
        xy = view.mission.items.get(seq)
        if xy is not None:
            item["x_m"], item["y_m"] = round(xy[0], 3), round(xy[1], 3)
            name = _target_name(xy, grid_map)
            if name:
                item["target"] = name
        reached_items.append(item)
    faults = _episodes(rec.fault_events)
    return {
        "tlog": rec.path,
        "messages": rec.messages,
        "vehicle_sysid": view.sysid,
        "policy_id": view.policy_id,
        "clock": CLOCK_NAMES[rec.clock],
        # SYSTEM_TIME.time_unix_usec of the last one read: the robot's own wall clock, "unset" if it has none
        "robot_wall_clock": _robot_wall_clock(view.robot_unix_us),
        "duration_s": round(rec.t_end, 3),
        "wall_duration_s": round(rec.wall_s, 3),
        "ignored": {"other_systems": {str(k): v for k, v in sorted(view.foreign.items())},
                    "clock_behind_frames": view.time_conflicts, "reboots": view.reboots},
        # from the first move (the controller DRIVING), as `qnav demo`'s sim_seconds, not from arming
        # (the operator's delay); from arming only for a robot that does not report its state
        "time_to_last_goal_s": (round(goal_times[-1] - (rec.first_driving if rec.first_driving is not None
                                                        else rec.first_armed or 0.0), 3) if goal_times else None),
        "goals_reached": len(goal_times),
        "mission_items_reached": reached_items,
        "guided_goals_reached_s": [round(t, 3) for t in guided],
        "mission_total": view.mission.total,
        # reached items including those before the recording began (implied by the robot's reports)
        "mission_items_done": view.mission_reached_count,
        "path_length_m": round(path_len, 3),
        "stops": len(_stops(rec)),
        "stop_list": _stops(rec),
        "faults": len(faults),
        "fault_list": faults,
        "link": {"packets": view.link.received, "lost": view.link.lost, "loss_pct": round(view.link.loss_pct, 3),
                 "signed": view.link.signing},
        "actions": {str(a): rec.actions.count(a) for a in sorted(set(rec.actions))},
        "actions_source": "NAMED_VALUE_INT ACTION samples (telemetry rate, not every control tick)",
        "timing": _timing(rec),
    }


def _timing(rec: RunRecord) -> dict:
    if not rec.load_pct:
        return {"available": False,
                "reason": "the recording has no SYS_STATUS from the vehicle (load, tick overruns)"}
    vals = sorted(v for _, v in rec.load_pct)
    n = len(vals)
    first, last = rec.overruns[0][1], rec.overruns[-1][1]
    return {"available": True,
            "source": "SYS_STATUS load (robot CPU) and errors_count2 (tick overruns); "
                      "per-tick times are not sent by the robot",
            "samples": n, "mean_load_pct": round(sum(vals) / n, 2), "p50_load_pct": vals[n // 2],
            "max_load_pct": vals[-1], "control_period_us": robot_spec.CONTROL_PERIOD_US,
            "tick_overruns": last - first if last >= first else last, "tick_overruns_total": last}


def write_report(rec: RunRecord, out_dir: str | os.PathLike[str], grid_map=None) -> dict:
    """Write the PNGs and summary.json into out_dir; return the summary."""
    from ground_station.plotting import png_bytes, pyplot

    plt = pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(rec, grid_map)
    plots: dict[str, str] = {}
    skipped: dict[str, str] = {}

    def save(name: str, fig, ax, xlabel: str, ylabel: str, title: str) -> None:  # type: ignore[no-untyped-def]
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        path = out / f"{name}.png"
        atomic_write(path, png_bytes(fig, dpi=110, bbox_inches="tight"))
        plots[name] = str(path)

    # trajectory over the map
    if rec.pose:
        fig, ax = plt.subplots(figsize=(6, 6))
        if grid_map is not None:
            c = grid_map.cell_size_m
            ax.imshow(grid_map.occ, cmap="Greys", origin="upper", vmin=0, vmax=1.4,
                      extent=(0, grid_map.width * c, 0, grid_map.height * c))
            for name, (col, row) in grid_map.targets.items():
                x, y = (v / 1000 for v in robot_spec.cell_center_mm(col, row, grid_map.height, int(round(c * 1000))))
                ax.plot(x, y, "s", color="gold", ms=12, mec="k")
                ax.annotate(name, (x, y), ha="center", va="center", fontweight="bold")
        for seq, (x, y) in sorted(rec.view.mission.items.items()):
            ax.plot(x, y, "o", mfc="none", mec="tab:orange", ms=16)
            ax.annotate(str(seq), (x, y), xytext=(8, 8), textcoords="offset points", color="tab:orange")
        xs, ys = [p[1] for p in rec.pose], [p[2] for p in rec.pose]
        ax.plot(xs, ys, "-", color="tab:blue", lw=2, label=f"path {summary['path_length_m']:.2f} m")
        ax.plot(xs[0], ys[0], "o", color="tab:green", label="start")
        ax.plot(xs[-1], ys[-1], "X", color="tab:red", label="end")
        ax.set_aspect("equal")
        ax.legend(loc="best", fontsize=8)
        save("trajectory", fig, ax, "x east [m]", "y north [m]",
             f"trajectory ({grid_map.name if grid_map is not None else 'no map'})")
    else:
        skipped["trajectory"] = "no LOCAL_POSITION_NED from the vehicle in the recording"

    if rec.distance:
        fig, ax = plt.subplots(figsize=(7, 3.5))
        ax.plot([d[0] for d in rec.distance], [d[1] for d in rec.distance], color="tab:blue")
        for t, seq in rec.mission_reached:
            ax.axvline(t, color="tab:green", ls="--", lw=1)
            ax.annotate(f"item {seq}", (t, 0), rotation=90, va="bottom", fontsize=8)
        for f in summary["fault_list"]:
            ax.axvspan(f["t_s"], f["t_s"] + 0.2, color="tab:red", alpha=0.4)
        save("distance_to_goal", fig, ax, "time [s]", "distance to goal [m]",
             "distance to goal (green: mission item reached, red: fault)")
    else:
        skipped["distance_to_goal"] = "no goal known while armed (no mission, POSITION_TARGET or NAV_CONTROLLER_OUTPUT)"

    if rec.actions:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        keys = sorted(set(rec.actions))
        ax.bar([str(k) for k in keys], [rec.actions.count(k) for k in keys], color="tab:purple")
        ax.xaxis.label.set_fontsize(7)  # the long label's size (kept when save sets its text)
        save("actions", fig, ax, "action index (sector: " + ", ".join(robot_spec.ACTION_NAMES)
             + "; cell: " + ", ".join(robot_spec.CELL_ACTION_NAMES) + ")", "telemetry samples", "actions")
    else:
        skipped["actions"] = "no policy decision in the recording (no ACTION NAMED_VALUE_INT >= 0)"

    if rec.load_pct:
        fig, ax = plt.subplots(figsize=(7, 3.5))
        ax.plot([t for t, _ in rec.load_pct], [v for _, v in rec.load_pct], color="tab:blue", label="load")
        ax.set_ylim(0, max(10.0, max(v for _, v in rec.load_pct) * 1.3))
        ax2 = ax.twinx()
        ax2.step([t for t, _ in rec.overruns], [v for _, v in rec.overruns], where="post", color="tab:red",
                 label="tick overruns")
        ax2.set_ylabel("tick overruns (cumulative)")
        ax2.set_ylim(bottom=0, top=max(1, max(v for _, v in rec.overruns)) * 1.2)
        fig.legend(loc="upper left", bbox_to_anchor=(0.0, 1.0), bbox_transform=ax.transAxes, fontsize=8)
        save("timing", fig, ax, "time [s]", "robot load [%]",
             f"control loop ({robot_spec.CONTROL_RATE_HZ} Hz): load and overruns (SYS_STATUS)")
    else:
        skipped["timing"] = summary["timing"]["reason"]

    summary["plots"] = plots
    summary["plots_skipped"] = skipped
    summary["map"] = grid_map.name if grid_map is not None else None
    atomic_write(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    summary["summary_json"] = str(out / "summary.json")
    return summary
