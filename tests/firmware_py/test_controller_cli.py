"""`qnav-robot` command line: help, one-line errors, and a wall-clock run on a
virtual bus that idles safely with no sensors."""

import json
import logging
from pathlib import Path

import pytest

from firmware_py import cli
from firmware_py.storage import ACTIVE_POLICY, Storage

PAPER10_CELL = Path(__file__).resolve().parents[2] / "policies" / "paper10_cell.qtab"


def test_help_lists_the_options(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for opt in ("--can", "--policy", "--lockstep", "--goal", "--storage", "--map-height", "--rt-priority"):
        assert opt in out


@pytest.mark.parametrize("argv, needle", [
    (["--can", "bogus"], "bad --can 'bogus'"),
    (["--policy", "/nonexistent.qtab"], "policy /nonexistent.qtab: cannot read"),
    (["--can", "virtual:x", "--goal", "1,2,3"], "--goal '1,2,3': expected 2 values"),
    (["--can", "virtual:x", "--goal-cell", "1,2"], "--goal-cell needs --map-height"),
    (["--can", "virtual:x", "--start", "a,b"], "--start 'a,b': expected numbers"),
    (["--can", "virtual:x", "--rate", "0"], "--rate 0: expected 1..100 Hz"),
    (["--can", "virtual:x", "--rate", "101"], "--rate 101: expected 1..100 Hz"),  # CTRL_RATE_HZ's bounds
    # the policy file records what it was trained for; the robot names both values
    (["--policy", str(PAPER10_CELL), "--rate", "25"],
     f"policy {PAPER10_CELL}: policy control period 50000 us != robot 40000 us"),
    (["--policy", str(PAPER10_CELL), "--cell-size", "0.25"], "policy cell size 500 mm != robot 250 mm"),
    (["--policy", str(PAPER10_CELL), "--map-height", "12"], "policy grid height 10 != robot --map-height 12"),
])
def test_bad_input_is_one_line_and_exit_2(capsys, argv, needle):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("qnav-robot: error: ") and needle in err[0]


def test_wall_clock_run_without_sensors_stays_in_standby(tmp_path, capsys):
    stats = tmp_path / "s.json"
    rc = cli.main(["--can", "virtual:cli-idle", "--duration", "0.3", "--stats-json", str(stats), "-q"])
    assert rc == 0
    s = json.loads(stats.read_text())
    assert s["state"] == "STANDBY"
    assert s["ticks"] >= 3  # the wall-clock loop ticked at 20 Hz
    assert s["transitions"][0][1:3] == ["BOOT", "STANDBY"]


def test_goal_without_sensors_times_out_unarmed(tmp_path):
    stats = tmp_path / "s.json"
    rc = cli.main(["--can", "virtual:cli-goal", "--goal", "1,1", "--duration", "0.3",
                   "--stats-json", str(stats), "-q"])
    assert rc == 4  # goals pending when the duration ended
    assert json.loads(stats.read_text())["state"] == "STANDBY"  # never armed: inputs stale


def test_boot_from_storage_skips_a_policy_for_another_period(tmp_path, caplog):
    Storage(tmp_path / "store").write_atomic(ACTIVE_POLICY, PAPER10_CELL.read_bytes())
    stats = tmp_path / "s.json"
    with caplog.at_level(logging.WARNING, logger="qnav.robot"):
        rc = cli.main(["--can", "virtual:cli-period", "--storage", str(tmp_path / "store"), "--mavlink", "none",
                       "--rate", "25", "--duration", "0.2", "--stats-json", str(stats), "-q"])
    assert rc == 0
    assert any("rejected: policy control period 50000 us != robot 40000 us" in r.getMessage() for r in caplog.records)
    s = json.loads(stats.read_text())
    assert s["period_us"] == 40_000 and s["state"] == "STANDBY"


def test_a_mavlink_port_in_use_or_a_missing_serial_device_is_one_line_and_exit_2(tmp_path, capsys):
    """Another program on the --mavlink port (or two robots started on one) and a serial device
    that is not there: one line naming the link and why, exit 2 (it was a traceback, exit 1)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        url = f"udpin:127.0.0.1:{port}"
        assert cli.main(["--can", "virtual:cli-port", "--storage", str(tmp_path), "--mavlink", url, "-q"]) == 2
    err = [x for x in capsys.readouterr().err.splitlines() if x.startswith("qnav-robot: error: ")]
    assert len(err) == 1 and f"--mavlink {url}: Address already in use" in err[0], err
    missing = str(tmp_path / "ttyNONE0")
    assert cli.main(["--can", "virtual:cli-tty", "--storage", str(tmp_path), "--mavlink", missing, "-q"]) == 2
    err = [x for x in capsys.readouterr().err.splitlines() if x.startswith("qnav-robot: error: ")]
    assert len(err) == 1 and f"--mavlink {missing}: " in err[0], err
