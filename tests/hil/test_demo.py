"""`qnav demo` end to end, as CI and a user run it: real processes (hub,
qnav-sim, qnav-robot), real CAN through python-can-remote, real MAVLink over
UDP loopback, pymavlink's FTP client, pymunk. Then `qnav report` on the
demo's tlog. Also: a policy the robot refuses, and Ctrl-C mid-run, both
leaving no process behind."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from firmware_py.shipped_policies import shipped_policy
from ground_station.lab.rigs import other_processes
from ground_station.maps import load_map
from tests.support.mcap_check import check_layout_against_mcap, check_run_mcap

ROOT = Path(__file__).resolve().parents[2]
QNAV = [sys.executable, "-c", "import sys; from ground_station.cli import main; sys.exit(main())"]


def _processes_mentioning(text: str) -> list[str]:
    """Command lines of live processes that mention `text` (our run folder)."""
    found = []
    for pid, cmd in other_processes():
        if text not in cmd:
            continue
        try:
            state = next((ln.split()[1] for ln in Path(f"/proc/{pid}/status").read_text().splitlines()
                          if ln.startswith("State:")), "")
        except OSError:
            continue
        if state != "Z":
            found.append(f"{pid}: {cmd}")
    return found


def _assert_hub_stopped(url: str) -> None:
    host, port = url.removeprefix("ws://").rstrip("/").split(":")
    with pytest.raises(OSError), socket.create_connection((host, int(port)), timeout=2):
        pass


def _demo(out: Path, *extra: str, timeout: float = 110) -> subprocess.CompletedProcess:
    return subprocess.run([*QNAV, "demo", "--headless", "--json", "--out", str(out), *extra], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


@pytest.mark.slow
def test_demo_headless_json_reaches_all_targets_and_report_reads_its_tlog(tmp_path):
    out = tmp_path / "run"
    proc = _demo(out)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    assert summary["targets_reached"] == summary["targets_total"] == 4, summary
    assert summary["collisions"] == 0
    assert summary["result"] == "mission complete" and summary["ok"] is True
    assert 20 < summary["sim_seconds"] < 300  # four legs on a 5 m map, in robot (sim) time
    assert summary["wall_seconds"] > 0
    assert summary["policy_id"] == "0xb5d6060c"  # policies/paper10_cell.json: the shipped file went up
    for key in ("tlog", "can_log", "trajectory_png", "trajectory_csv", "robot_stats", "mcap"):
        assert summary[key] and Path(summary[key]).stat().st_size > 0, key
    assert json.loads((out / "summary.json").read_text()) == summary
    # run.mcap: the whole run, read back with the mcap package's reader (tests/support/mcap_check.py)
    topics = check_run_mcap(Path(summary["mcap"]), Path(summary["tlog"]), Path(summary["can_log"]),
                            Path(summary["trajectory_csv"]), load_map(summary["map"]))
    assert topics["/mission"] == 4 and topics["/log"] > 0 and topics["/location"] > 0
    check_layout_against_mcap(ROOT / "ground_station" / "logs" / "foxglove_layout.json", Path(summary["mcap"]))
    # the processes were stopped by the demo (SIGINT -> 130), none is left, the hub is gone
    assert summary["exit_codes"] == {"sim": 130, "robot": 130}
    assert _processes_mentioning(str(out)) == []
    _assert_hub_stopped(summary["can_hub"])
    # the robot really activated the uploaded file and drove the mission
    stats = json.loads(Path(summary["robot_stats"]).read_text())
    causes = [t[3] for t in stats["transitions"]]
    assert "mission complete" in causes and not any("FAULT" in t[2] for t in stats["transitions"])
    # every counter of refused input is in the file (issue 29 finding 8), none raised in a clean run
    assert stats["refused_clock_jumps"] == 0 and stats["encoder_jumps"] == 0 and stats["param_save_errors"] == 0
    assert stats["foreign_gcs_heartbeats"] == 0
    assert (out / "robot" / "policies" / "active.qtab").read_bytes() == shipped_policy("paper10_cell").read_bytes()

    rep = subprocess.run([*QNAV, "report", summary["tlog"], "--out", str(tmp_path / "report"), "--json"],
                         cwd=ROOT, capture_output=True, text=True, timeout=110)
    assert rep.returncode == 0, rep.stderr[-2000:]
    report = json.loads(rep.stdout)
    assert report["goals_reached"] == 4, report
    for name in ("trajectory", "distance_to_goal", "actions", "timing"):
        png = Path(report["plots"][name])
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    assert json.loads(Path(report["summary_json"]).read_text())["goals_reached"] == 4
    # issue 15 item 3: the report runs on the robot's (sim) clock, as the demo's own figure
    assert report["clock"].startswith("robot time_boot_ms"), report["clock"]
    assert report["time_to_last_goal_s"] == pytest.approx(summary["sim_seconds"], abs=1.0)
    assert report["wall_duration_s"] < report["duration_s"]  # lockstep runs faster than real time
    assert report["robot_wall_clock"] not in (None, "unset")  # SYSTEM_TIME with this host's set clock
    # issue 15 item 2: the decision in force is held while DRIVING (a cell policy decides once per
    # cell move), so the action histogram and the monitor's policy panel have real data
    assert sum(report["actions"].values()) >= 50, report["actions"]
    held = _state_idx_while_driving(Path(summary["tlog"]))
    assert len(held) >= 50 and sum(v >= 0 for v in held) >= 0.95 * len(held), held
    assert (out / "can.log").read_text().startswith("(") and summary["can_log_candump"] == str(out / "can.log")
    # a monitor attached mid-mission (the second half of the recording) ends with the whole mission
    half = tmp_path / "half.tlog"
    half.write_bytes(_second_half(Path(summary["tlog"])))
    mon = subprocess.run([*QNAV, "monitor", "--replay", str(half), "--plain", "--speed", "0"],
                         cwd=ROOT, capture_output=True, text=True, timeout=110)
    assert mon.returncode == 0, mon.stderr[-2000:]
    assert "mission=4/4 reached=4" in mon.stdout.splitlines()[-1], mon.stdout[-500:]


def _state_idx_while_driving(tlog: Path) -> list[int]:
    """The robot's STATE_IDX samples sent while its CTRL_ST said DRIVING."""
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    from firmware_py.vehicle import CtrlState

    log = mavutil.mavlogfile(str(tlog), robust_parsing=True)
    ctrl, out = None, []
    while (msg := log.recv_msg()) is not None:
        if msg.get_type() != "NAMED_VALUE_INT" or msg.get_srcSystem() != 1:
            continue
        name = msg.name.decode() if isinstance(msg.name, bytes) else msg.name
        if name == "CTRL_ST":
            ctrl = msg.value
        elif name == "STATE_IDX" and ctrl == CtrlState.DRIVING:
            out.append(msg.value)
    log.close()
    return out


def _second_half(tlog: Path) -> bytes:
    """The records of a .tlog from its middle on, cut at a record boundary."""
    import struct

    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    log = mavutil.mavlogfile(str(tlog), robust_parsing=True)
    recs = []
    while (msg := log.recv_msg()) is not None:
        if msg.get_type() != "BAD_DATA":
            recs.append(struct.pack(">Q", int(msg._timestamp * 1e6) & ~3) + bytes(msg.get_msgbuf()))
    log.close()
    return b"".join(recs[len(recs) // 2:])


def test_demo_refused_policy_fails_with_the_robots_reason_and_cleans_up(tmp_path):
    bad = tmp_path / "bad.qtab"
    data = bytearray(shipped_policy("paper10_cell").read_bytes())
    data[len(data) // 2] ^= 0xFF  # CRC no longer matches: the robot's loader must refuse it
    bad.write_bytes(bytes(data))
    out = tmp_path / "run"
    proc = _demo(out, "--policy", str(bad))
    assert proc.returncode == 1, proc.stderr[-3000:]
    summary = json.loads(proc.stdout)
    assert summary["ok"] is False and summary["targets_reached"] == 0
    assert summary["result"].startswith("error: policy upload:"), summary["result"]
    assert "crc" in summary["result"].lower(), summary["result"]
    assert not (out / "robot" / "policies" / "active.qtab").exists()
    assert _processes_mentioning(str(out)) == []


def test_demo_ctrl_c_stops_every_process(tmp_path):
    out = tmp_path / "run"
    # paced at real time (83 s of mission): Ctrl-C lands mid-mission. In lockstep the whole mission takes
    # ~6 s of wall time, and on a loaded machine it once ended before the signal (exit 0, "mission complete")
    proc = subprocess.Popen([*QNAV, "demo", "--headless", "--json", "--realtime", "--out", str(out)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        # wait until the sim and the robot are both up
        while time.monotonic() < deadline and proc.poll() is None:
            line = proc.stderr.readline()
            if "robot sysid" in line:
                break
        assert proc.poll() is None, "demo ended before the robot was found"
        assert len(_processes_mentioning(str(out))) >= 2  # qnav-sim and qnav-robot
        proc.send_signal(signal.SIGINT)
        try:
            stdout, _ = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:  # where each process is: their stacks in their logs
            from tests.support.hang import stacks_and_logs

            pids = [proc.pid] + [int(line.split(":")[0]) for line in _processes_mentioning(str(out))]
            report = stacks_and_logs(pids, out)
            proc.kill()
            _, said = proc.communicate()  # all its stderr since the robot was found (communicate loses none)
            pytest.fail(f"qnav demo still running 60 s after SIGINT:\n{said[-4000:]}\n{report}")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130
    assert _processes_mentioning(str(out)) == []
    summary = json.loads(stdout)  # still reported: what ran, where its outputs are
    assert summary["result"] == "interrupted" and summary["ok"] is False
    _assert_hub_stopped(summary["can_hub"])


def test_demo_bad_arguments_are_one_line_errors(tmp_path):
    for args, needle in ((["--targets", "A,Z"], "Z"), (["--policy", str(tmp_path / "nope.qtab")], "nope.qtab"),
                         (["--policy", "policies:nope"], "no shipped policy 'nope'"),
                         (["--timeout", "0"], "--timeout")):
        proc = subprocess.run([*QNAV, "demo", "--headless", "--out", str(tmp_path / "r"), *args], cwd=ROOT,
                              capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2, (args, proc.stderr)
        errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("qnav demo: error:")]
        assert len(errors) == 1 and needle in errors[0], proc.stderr


def test_demo_dashboard_path_runs_the_monitor_until_the_mission_completes(tmp_path, monkeypatch):
    # what `make demo` shows in a terminal: MonitorApp on the live link, closing
    # itself at the end; textual's headless driver stands in for the terminal
    from textual.app import App

    from firmware_py import robot_spec
    from ground_station.demo import DemoOptions, run_demo
    from ground_station.maps import load_map
    from ground_station.monitor.app import (
        MonitorApp,
        render_log,
        render_map,
        render_mission,
        render_vehicle,
    )

    shown = {}
    real_run = App.run

    def run_headless(self, *args, **kwargs):
        assert isinstance(self, MonitorApp)
        result = real_run(self, headless=True)
        # the panels are pure functions of the view the dashboard fed while it ran
        shown["map"] = render_map(self.view, self.grid_map).plain
        shown["vehicle"] = render_vehicle(self.view).plain
        shown["mission"] = render_mission(self.view, self.grid_map).plain
        shown["log"] = render_log(self.view, lines=100).plain
        shown["pose"] = self.view.pose
        shown["clock"] = (self.view.time_conflicts, self.view.reboots, self.view.link.lost)
        return result

    monkeypatch.setattr(App, "run", run_headless)
    out = tmp_path / "run"
    # two targets, B then D (the headless test above runs the whole A-D mission): the dashboard's path
    # from the first item to "mission complete" is the same for two items as for four
    summary = run_demo(DemoOptions(out=out, headless=False, targets=("B", "D")))
    assert summary.result == "mission complete" and summary.ok, summary
    assert summary.targets_reached == 2 and summary.collisions == 0
    # the dashboard saw the run: Auto, every item reached, then Hold at D, still armed; the map drawn
    assert "mode Hold" in shown["vehicle"] and "ARMED" in shown["vehicle"], shown["vehicle"]
    assert "reached 2" in shown["mission"], shown["mission"]
    assert "GOAL_REACHED->HOLD: mission complete" in shown["log"], (shown["log"], "time conflicts, reboots, lost:",
                                                                     shown["clock"])
    d = robot_spec.cell_center_mm(*load_map("paper10").targets["D"], 10)
    assert abs(shown["pose"][0] - d[0] / 1000) < 0.3 and abs(shown["pose"][1] - d[1] / 1000) < 0.3, \
        (shown["pose"], "time conflicts, reboots, lost frames:", shown["clock"])
    assert "A" in shown["map"] and "██" in shown["map"]
    assert _processes_mentioning(str(out)) == []
    _assert_hub_stopped(summary.can_hub)
