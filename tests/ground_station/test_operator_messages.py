"""Issue 30 finding 7's smaller items: what an operator reads when something is
wrong says it once, names the place, and suggests the fix."""

from __future__ import annotations

import argparse
import contextlib
import io

import pytest

from ground_station.errors import CliError
from ground_station.mavlink import link as link_module
from ground_station.mavlink.link import LinkError, default_tlog_path, run_on_link
from ground_station.mavlink.mission_items import file_items
from tests.firmware_py.test_mav_engines import Link, texts


def test_an_unknown_parameter_name_gets_the_closest_one():
    robot = Link()
    said = texts(robot.send(robot.gcs.param_set_encode(1, 1, b"GOAL_TOLMM", 300, 6)))
    assert "unknown parameter GOAL_TOLMM (did you mean GOAL_TOL_MM?)" in "".join(said), said
    said = texts(robot.send(robot.gcs.param_request_read_encode(1, 1, b"NOTHING_LIKE", -1)))
    assert "".join(said) == "unknown parameter NOTHING_LIKE"


def test_session_logs_have_no_spaces_in_their_names():
    assert " " not in default_tlog_path("mission download").name


def test_a_refusal_is_not_prefixed_twice(monkeypatch):
    @contextlib.contextmanager
    def fake_link(_args, _name):
        yield None

    monkeypatch.setattr(link_module, "open_link", fake_link)

    def body(_link):
        raise LinkError(3, "mission upload: DENIED: item 1: goal cell (0,0) is not a policy target")

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = run_on_link(argparse.Namespace(), "mission upload", body)
    assert code == 3
    assert err.getvalue() == "qnav mission upload: DENIED: item 1: goal cell (0,0) is not a policy target\n"


def test_a_bad_waypoint_file_names_its_line(tmp_path):
    wpl = tmp_path / "m.txt"
    wpl.write_text("QGC WPL 110\n0\t1\t1\t16\t0\t0\t0\t0\t1.0\t2.0\t0\t1\n1\t0\t1\t16\t0\t0\t0\t0\tabc\t2.0\t0\t1\n")
    with pytest.raises(CliError, match=r"m\.txt:3: field 9 'abc' is not a number"):
        file_items(str(wpl))
    wpl.write_text("QGC WPL 110\n0\t1\t1\t16\t0\n")
    with pytest.raises(CliError, match=r"m\.txt:2: 5 fields, a QGC WPL 110 item has 12"):
        file_items(str(wpl))
