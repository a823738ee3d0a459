"""`qnav-robot` command line: help, one-line errors, and a wall-clock run on a
virtual bus that idles safely with no sensors."""

import json

import pytest

from firmware_py import cli


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
