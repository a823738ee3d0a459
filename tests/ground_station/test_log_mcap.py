"""`qnav log mcap` on a scripted tlog (tests/support/rover_script.py): every
MAVLink frame on its `/mavlink/<TYPE>` topic, the robot's pose on `/pose` at
its own time_boot_ms, the mission from the GCS's items, the map as a Grid;
bad input is a one-line error with exit 2 and no file left behind."""

from __future__ import annotations

from collections import Counter

from mcap.reader import make_reader

from tests.support.cli import run_qnav
from tests.support.rover_script import RoverScript, write_tlog


def qnav(*argv: str) -> tuple[int, str]:
    code, out, err = run_qnav(*argv)
    return code, err + out


def test_a_tlog_becomes_an_mcap_on_the_robot_clock(tmp_path):
    script = RoverScript()
    tlog = tmp_path / "run.tlog"
    frames = write_tlog(tlog, script)
    code, out = qnav("log", "mcap", str(tlog), "--map", "paper10")
    assert code == 0, out
    counts: Counter[str] = Counter()
    pose_ns = []
    with open(tmp_path / "run.mcap", "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            counts[channel.topic] += 1
            if channel.topic == "/pose":
                assert schema.name == "foxglove.PoseInFrame"
                pose_ns.append(message.log_time)
    assert sum(n for t, n in counts.items() if t.startswith("/mavlink/")) == frames
    want = [m.time_boot_ms * 1_000_000 for _t, m in script.stream() if m.get_type() == "LOCAL_POSITION_NED"]
    assert pose_ns == want  # the robot's clock, not the tlog's receive stamps
    assert counts["/map"] == 1 and counts["/mission"] > 0 and counts["/scan"] > 0 and counts["/log"] > 0
    assert f"{frames} MAVLink messages" in out


def test_bad_input_is_one_line_and_leaves_no_file(tmp_path):
    tlog = tmp_path / "run.tlog"
    write_tlog(tlog, RoverScript())
    for argv, needle in ((["log", "mcap", str(tmp_path / "nope")], "no such run folder or tlog"),
                         (["log", "mcap", str(tlog), "--can", str(tmp_path / "x.blf")], "--can"),
                         (["log", "mcap", str(tlog), "--map", "nope"], "--map nope"),
                         (["log", "mcap", str(tmp_path)], "no .tlog and no can.blf in the run folder")):
        if argv[2] == str(tmp_path):
            tlog.rename(tmp_path / "moved.bin")
        code, out = qnav(*argv)
        errors = [ln for ln in out.splitlines() if ln.startswith("qnav log: error:")]
        assert code == 2 and len(errors) == 1 and needle in errors[0], out
    assert not list(tmp_path.glob("*.mcap")) and not list(tmp_path.glob(".*.part"))
