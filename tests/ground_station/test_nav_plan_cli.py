"""`qnav mission upload --plan` and `qnav goal --plan` over real UDP loopback
against the MAVLink node with the test vehicle (tests/support/mav_vehicle.py):
the planner's waypoints (ground_station/maps/planner.py) go up as the
mission, from the robot's reported position or `--start`."""

from __future__ import annotations

import math

import pytest

from firmware_py import robot_spec
from firmware_py.vehicle import Mode
from ground_station.maps import load_map
from ground_station.maps.planner import plan_waypoints
from tests.ground_station.test_mav_link import qnav, rig  # noqa: F401 (fixture)


def _centre(col: int, row: int) -> tuple[int, int]:
    return robot_spec.cell_center_mm(col, row, 10)


def test_mission_upload_plan_from_the_robot_position(rig):  # noqa: F811
    port, start, _tmp = rig
    r = start()
    r.vehicle.st.x_mm, r.vehicle.st.y_mm = 2750, 2750  # cell (5, 4) of paper10
    code, out = qnav(port, "mission", "upload", "--targets", "A,B", "--plan", "--map", "paper10")
    assert code == 0, out
    gm = load_map("paper10")
    leg1 = plan_waypoints(gm, (2750, 2750), (2, 2), start_mm=True)
    # by hand: (5, 4) has walls north (5, 3) and west (4, 4); east to (6, 4), north to row 2 over (6, 3),
    # then west along row 2 to A (2, 2) in segments of at most 1 m (DEFAULT_MAX_SEGMENT_MM)
    assert leg1 == [_centre(6, 4), _centre(6, 2), _centre(4, 2), _centre(2, 2)]
    leg2 = plan_waypoints(gm, (2, 2), (9, 0))
    want = [(round(x), round(y)) for x, y in leg1 + leg2]
    got = r.vehicle.mission
    assert len(got) == len(want) > 2
    # lat/lon around the robot's origin: back within 6 mm (1e-7 deg steps) + 1 mm of rounding
    assert all(math.dist(a, b) <= 7 for a, b in zip(got, want, strict=True))
    assert math.dist(got[len(leg1) - 1], _centre(2, 2)) <= 7 and math.dist(got[-1], _centre(9, 0)) <= 7
    assert f"targets at items {len(leg1) - 1}, {len(want) - 1}" in out


def test_mission_upload_plan_from_start_and_bad_input(rig):  # noqa: F811
    port, start, _tmp = rig
    r = start()
    code, out = qnav(port, "mission", "upload", "--targets", "C", "--plan", "--start", "0.25,0.25", "--map", "paper10")
    assert code == 0, out
    assert math.dist(r.vehicle.mission[-1], _centre(0, 9)) < 7 and len(r.vehicle.mission) == 1  # C is the start cell
    assert qnav(port, "mission", "upload", "--plan", "some.waypoints")[0] == 2  # --plan needs --targets
    code, out = qnav(port, "mission", "upload", "--targets", "A", "--plan", "--start", "nope")
    assert code == 2 and "--start" in out


def test_goal_plan_uploads_the_planned_mission_and_starts_it(rig):  # noqa: F811
    port, start, _tmp = rig
    r = start()
    r.vehicle.st.x_mm, r.vehicle.st.y_mm = 250, 250  # cell (0, 9)
    assert qnav(port, "arm")[0] == 0
    code, out = qnav(port, "goal", "4.7", "4.8", "--plan", "--map", "paper10")
    assert code == 0, out
    assert len(r.vehicle.mission) > 2 and r.vehicle.mission[-1] == (4700, 4800)
    assert r.vehicle.st.mode == Mode.AUTO
    code, out = qnav(port, "goal", "0.75", "4.25", "--plan", "--map", "paper10")  # (1, 1) is an obstacle cell of paper10
    assert code == 2 and "not in a free cell" in out


def _run(*argv: str) -> tuple[int, str]:
    """qnav in-process without a robot: the input is refused before any link opens."""
    import contextlib
    import io

    from ground_station import cli

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(err):
        try:
            code = cli.main([*argv, "--mavlink", "udpin:127.0.0.1:9", "--timeout", "0.2", "--no-tlog"])
        except SystemExit as exc:  # argparse's own refusal
            code = int(exc.code or 0)
    return code, err.getvalue()


@pytest.mark.parametrize("argv, says", [
    (["goal", "nan", "1"], "argument X: must be a finite number, got nan"),
    (["goal", "1", "inf", "--plan"], "argument Y: must be a finite number, got inf"),
    (["goal", "1", "1e300"], "out of range"),
    (["goal", "4.7", "4.8", "--plan", "--start", "nan,1"], "--start must be X,Y in metres"),
    (["goal", "1", "1", "--start", "1,1"], "--start needs --plan"),
    (["mission", "upload", "--targets", "A", "--plan", "--start", "1,inf"], "--start must be X,Y in metres"),
    (["mission", "upload", "--targets", "A", "--start", "1,1"], "--start needs --plan"),
])
def test_non_finite_goal_and_start_are_refused_with_one_line(argv, says):
    code, err = _run(*argv)
    assert code == 2 and says in err, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].count("error") == 1


def test_mission_upload_plan_keeps_the_profiles_body_clear(rig, tmp_path):  # noqa: F811
    """--profile FILE.toml: the planner's segments keep the profile's body (wide_six: 180 mm) clear, as
    `qnav train --profile` trained its sector policy with, instead of the built-in 150 mm."""
    import numpy as np

    from ground_station.maps.planner import DEFAULT_MARGIN_MM, segment_clear

    wide = str(robot_spec.__file__).replace("robot_spec.py", "profiles/wide_six.toml")
    port, start, _tmp = rig
    r = start()
    r.vehicle.st.x_mm, r.vehicle.st.y_mm = 2750, 2750  # cell (5, 4) of paper10
    code, out = qnav(port, "mission", "upload", "--targets", "A,B", "--plan", "--map", "paper10", "--profile", wide)
    assert code == 0, out
    gm = load_map("paper10")
    leg1 = plan_waypoints(gm, (2750, 2750), (2, 2), start_mm=True, radius_mm=180)
    want = leg1 + plan_waypoints(gm, (2, 2), (9, 0), radius_mm=180)
    assert want != plan_waypoints(gm, (2750, 2750), (2, 2), start_mm=True) + plan_waypoints(gm, (2, 2), (9, 0))
    got = r.vehicle.mission
    assert len(got) == len(want) and all(math.dist(a, b) <= 7 for a, b in zip(got, want, strict=True))
    occ = np.ascontiguousarray(gm.occ, dtype=np.uint8)

    def long_segments_clear(wps: list, r: float) -> bool:  # a step to a neighbouring cell is the fallback
        return all(segment_clear(occ, gm.height, gm.width, 500.0, *a, *b, r + DEFAULT_MARGIN_MM)
                   for a, b in zip(wps, wps[1:], strict=False) if math.dist(a, b) > 710)

    leg2 = want[len(leg1) - 1:]  # from A's centre
    assert long_segments_clear(leg2, 180) and long_segments_clear(plan_waypoints(gm, (2, 2), (9, 0)), 150)
    assert not long_segments_clear(plan_waypoints(gm, (2, 2), (9, 0)), 180)  # the built-in plan: too close
    assert f"planned {len(want)} waypoints for a 180 mm body" in out
    bad = tmp_path / "bad.toml"
    bad.write_text("[geometry]\nrobot_radius_mm = 'wide'\n")
    code, err = _run("mission", "upload", "--targets", "A", "--plan", "--profile", str(bad))
    assert code == 2 and "robot_radius_mm" in err and "Traceback" not in err, err
    code, err = _run("mission", "upload", "--targets", "A", "--profile", wide)
    assert code == 2 and "--profile needs --plan" in err, err


def test_goal_plan_keeps_the_profiles_body_clear(rig, tmp_path):  # noqa: F811
    """`qnav goal X Y --plan --profile FILE.toml` plans the mission for the profile's body (wide_six:
    180 mm), as `qnav mission upload --plan --profile` does, instead of the built-in 150 mm; the same
    flag, help and one-line refusals."""
    from ground_station.mavlink.mission_items import planned_goal_items

    wide = str(robot_spec.__file__).replace("robot_spec.py", "profiles/wide_six.toml")
    port, start, _tmp = rig
    r = start()
    r.vehicle.st.x_mm, r.vehicle.st.y_mm = 2750, 2750  # cell (5, 4) of paper10
    assert qnav(port, "arm")[0] == 0
    code, out = qnav(port, "goal", "4.7", "4.8", "--plan", "--map", "paper10", "--profile", wide)
    assert code == 0, out
    gm = load_map("paper10")
    want = [(it[2] / 10, it[1] / 10) for it in planned_goal_items(gm, 4.7, 4.8, (2750, 2750), 180)]  # 0.1 mm
    built_in = [(it[2] / 10, it[1] / 10) for it in planned_goal_items(gm, 4.7, 4.8, (2750, 2750))]
    assert len(want) != len(built_in)  # measured: 8 waypoints for the 180 mm body, 5 for the built-in
    got = r.vehicle.mission
    assert len(got) == len(want) and all(math.dist(a, b) <= 7 for a, b in zip(got, want, strict=True)), (got, want)
    assert f"mission of {len(want)} planned waypoints for a 180 mm body accepted, mode Auto" in out
    assert r.vehicle.st.mode == Mode.AUTO
    bad = tmp_path / "bad.toml"
    bad.write_text("[geometry]\nrobot_radius_mm = 'wide'\n")
    code, err = _run("goal", "4.7", "4.8", "--plan", "--profile", str(bad))
    assert code == 2 and "--profile" in err and "robot_radius_mm" in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
    code, err = _run("goal", "4.7", "4.8", "--profile", wide)
    assert code == 2 and "--profile needs --plan" in err, err


def test_mission_follow_replans_for_the_profiles_body(rig, monkeypatch):  # noqa: F811
    """`qnav mission upload --plan --follow --profile FILE.toml`: the follower re-plans for the profile's
    body (its radius reaches `MissionFollower`) and places the readings at its sensors' angles, the
    built-in 150 mm and eight sensors without --profile."""
    import ground_station.nav.replan as replan

    wide = str(robot_spec.__file__).replace("robot_spec.py", "profiles/wide_six.toml")
    seen: list[float] = []
    sensors: list[tuple[int, ...]] = []

    def follow(link, follower, timeout_s, say):  # noqa: ANN001
        seen.append(follower.radius_mm)
        assert follower.seen is not None and follower.seen.layout == follower.layout
        sensors.append(follower.layout.angles_mrad)
        return replan.Finished(True, "stub")

    monkeypatch.setattr(replan, "follow_mission", follow)
    port, start, _tmp = rig
    r = start()
    r.vehicle.st.x_mm, r.vehicle.st.y_mm = 2750, 2750
    for extra in (["--profile", wide], []):
        code, out = qnav(port, "mission", "upload", "--targets", "A", "--plan", "--follow", "--map", "paper10",
                         *extra)
        assert code == 0, out
    assert seen == [180.0, robot_spec.ROBOT_RADIUS_MM]
    assert sensors == [(0, 698, -873, 1658, -1484, 3142), robot_spec.SENSOR_ANGLES_MRAD]  # wide_six's 0/40/-50/95/-85/180
