"""qnav report on tlogs generated here with pymavlink (scripted rover run)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import matplotlib.image as mpimg
import pytest

from ground_station.maps import load_map
from ground_station.monitor.report import analyse, write_report
from tests.support.rover_script import (
    FAULT_S,
    PATH_LENGTH_M,
    STOP_AT_A_S,
    T_ARM,
    RoverScript,
    write_tlog,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def full_tlog(tmp_path_factory):
    path = tmp_path_factory.mktemp("tlog") / "run.tlog"
    write_tlog(path, RoverScript())
    return path


def test_summary_matches_the_scripted_run(full_tlog, tmp_path):
    script = RoverScript()
    s = write_report(analyse(full_tlog), tmp_path, load_map("paper10"))
    assert s["goals_reached"] == 2
    assert [(i["seq"], i.get("target")) for i in s["mission_items_reached"]] == [(0, "A"), (1, "B")]
    assert s["mission_items_reached"][0]["t_s"] == pytest.approx(script.t_reach_a, abs=0.11)
    assert s["time_to_last_goal_s"] == pytest.approx(script.t_reach_b - T_ARM, abs=0.11)
    assert s["duration_s"] == pytest.approx(script.t_end, abs=0.11)
    assert s["path_length_m"] == pytest.approx(PATH_LENGTH_M, abs=0.01)
    # the 1.5 s pause at A is a stop; the 0.5 s turns in place and the fault are not
    assert s["stops"] == 1
    assert s["stop_list"][0]["t_s"] == pytest.approx(script.t_reach_a, abs=0.11)
    assert s["stop_list"][0]["duration_s"] == pytest.approx(STOP_AT_A_S, abs=0.21)
    assert s["faults"] == 1
    fault = s["fault_list"][0]
    assert fault["t_s"] == pytest.approx(script.t_fault, abs=0.11)
    assert "controller entered FAULT" in fault["events"] and any("sensor timeout" in e for e in fault["events"])
    assert s["policy_id"] == 4242
    assert s["link"] == {"packets": s["link"]["packets"], "lost": 0, "loss_pct": 0.0, "signed": False}
    assert set(s["actions"]) == {"0", "1", "2"} and s["actions"]["0"] > s["actions"]["1"]
    assert s["timing"]["available"] and s["timing"]["source"].startswith("SYS_STATUS")
    assert s["timing"]["mean_load_pct"] == 15.0 and s["timing"]["tick_overruns"] == 2
    assert s["plots_skipped"] == {}
    for name in ("trajectory", "distance_to_goal", "actions", "timing"):
        path = tmp_path / f"{name}.png"
        assert s["plots"][name] == str(path)
        assert path.read_bytes()[:8] == PNG_MAGIC
        h, w = mpimg.imread(path).shape[:2]
        assert h > 100 and w > 100
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["goals_reached"] == 2 and on_disk["plots"] == s["plots"]
    assert not list(tmp_path.glob("*.tmp"))


def test_fault_lasts_and_gaps_do_not_merge_episodes(full_tlog):
    rec = analyse(full_tlog)
    times = sorted(t for t, _ in rec.fault_events)
    assert times[-1] - times[0] < FAULT_S  # one episode's events


def test_missing_timing_data_is_said_not_faked(tmp_path):
    tlog = tmp_path / "bare.tlog"
    write_tlog(tlog, RoverScript(), with_gcs_items=False, drop_types=("SYS_STATUS",))
    s = write_report(analyse(tlog), tmp_path / "out", None)
    assert s["timing"]["available"] is False and "SYS_STATUS" in s["timing"]["reason"]
    assert "timing" in s["plots_skipped"] and not (tmp_path / "out" / "timing.png").exists()
    assert s["map"] is None and (tmp_path / "out" / "trajectory.png").exists()
    # without the GCS's mission items the goals still count, just without target names
    assert s["goals_reached"] == 2 and all("target" not in i for i in s["mission_items_reached"])


def _qnav(*args):
    return subprocess.run([str(Path(sys.executable).parent / "qnav"), *args],
                          capture_output=True, text=True, timeout=60)


def test_cli_writes_report_and_prints_json(full_tlog, tmp_path):
    r = _qnav("report", str(full_tlog), "--out", str(tmp_path / "rep"), "--json", "--map", "paper10")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["goals_reached"] == 2 and s["map"] == "paper10"
    # issue 30 item 4: a tlog alone does not say its map: no guess (paper10 was drawn under any run)
    bare = _qnav("report", str(full_tlog), "--out", str(tmp_path / "bare"), "--json")
    assert bare.returncode == 0 and json.loads(bare.stdout)["map"] is None
    assert "no map given" in bare.stderr and "give --map" in bare.stderr
    assert sorted(p.name for p in (tmp_path / "rep").iterdir()) == [
        "actions.png", "distance_to_goal.png", "summary.json", "timing.png", "trajectory.png"]


def test_cli_rejects_bad_input(tmp_path):
    r = _qnav("report", str(tmp_path / "missing.tlog"))
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "no such tlog" in r.stderr
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(bytes(range(256)) * 8)
    r = _qnav("report", str(junk), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "no MAVLink messages" in r.stderr
    r = _qnav("report", str(junk), "--map", "no-such-map")
    assert r.returncode == 2 and "--map no-such-map" in r.stderr


def test_report_keeps_error_texts_whose_last_chunk_was_lost(tmp_path):
    """Two chunked ERROR texts lose their terminator: one mid-recording (it ends
    when other frames show its chunks stopped), one as the recording's last frame."""
    import struct

    from firmware_py.mavlink.dialect import mavlink2 as mavlink
    from tests.support.rover_script import encoder, frame

    rover = encoder(1, 1)
    hb = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GROUND_ROVER, mavlink.MAV_AUTOPILOT_GENERIC,
                                           mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, 3, 3)
    lost_mid, lost_end = "a" * 50, "b" * 50
    script = [(0.0, hb), (0.5, mavlink.MAVLink_statustext_message(3, lost_mid.encode(), 5, 0)),
              (1.0, hb), (2.0, hb), (2.5, mavlink.MAVLink_statustext_message(2, lost_end.encode(), 6, 0))]
    tlog = tmp_path / "lost.tlog"
    with open(tlog, "wb") as f:
        for t, msg in script:
            f.write(struct.pack(">Q", int((1_700_000_000.0 + t) * 1e6)) + frame(rover, msg))
    rec = analyse(tlog)
    assert [what for _, what in rec.fault_events] == [f"ERROR: {lost_mid}", f"CRIT: {lost_end}"]


def _report_cli(*argv: str) -> tuple[int, str]:
    import contextlib
    import io

    from ground_station import cli

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(list(argv))
    return code, err.getvalue()


def test_report_names_a_map_the_run_does_not_fit_and_takes_a_demo_runs_own(full_tlog, tmp_path):
    """Issue 30 finding 4: without --map a run on another map was drawn on paper10,
    through walls, without a word."""
    code, err = _report_cli("report", str(full_tlog), "--out", str(tmp_path / "a"), "--json")
    assert code == 0 and "warning" not in err  # the scripted run is on paper10: it fits
    code, err = _report_cli("report", str(full_tlog), "--out", str(tmp_path / "b"), "--json",
                            "--map", "maze-16x16-s1")
    assert code == 0
    (line,) = [ln for ln in err.splitlines() if "positions lie outside map" in ln]
    assert "maze-16x16-s1" in line and "give --map" in line
    # a demo run folder names its map in summary.json: taken without --map
    run = tmp_path / "run"
    run.mkdir()
    (run / "demo.tlog").write_bytes(full_tlog.read_bytes())
    (run / "summary.json").write_text(json.dumps({"map": "maze-16x16-s1"}))
    code, err = _report_cli("report", str(run / "demo.tlog"), "--out", str(tmp_path / "c"), "--json")
    assert code == 0 and "outside map maze-16x16-s1" in err
