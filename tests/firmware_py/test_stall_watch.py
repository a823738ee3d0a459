"""No silent stall (issue 44 item 5): a drive that neither gets closer to its goal nor moves for
NAV_STALL_S is reported (STATUSTEXT with the reason) and held (firmware_py/control/progress.py
StallWatch, Controller._drive ending the drive). The pure watch, then the controller on a kinematic plant; the
lockstep reproduction with the MAVLink node is tests/hil/test_stall_hil.py."""

from __future__ import annotations

from firmware_py.control.controller import Controller
from firmware_py.control.progress import NO_PROGRESS_US, STALL_MOVE_MM, ProgressWatch, StallWatch
from firmware_py.vehicle import CtrlState, Mode, VehicleConfig
from tests.firmware_py.test_progress_watch import _spinning_policy
from tests.support.controller_rig import Kinematic, Rig, sector_seek_policy

S = 1_000_000
TIMEOUT = 20 * S
KEY = ((5000, 250), 0)


def test_a_robot_standing_still_is_reported_once_per_window_after_the_timeout():
    w = StallWatch()
    assert w.update(0, KEY, 3000, 0, 0, TIMEOUT) is None
    for t in range(1, 20):
        w.note(False, False, (0, 0))
        assert w.update(t * S, KEY, 2990, 10, 0, TIMEOUT) is None  # 10 mm closer: not progress
    assert w.update(20 * S, KEY, 2990, 10, 0, TIMEOUT) == "no progress"
    assert w.count == 1
    assert w.update(21 * S, KEY, 2990, 10, 0, TIMEOUT) is None  # a new window begins


def test_a_detour_away_from_the_goal_is_progress_while_the_robot_moves():
    w = StallWatch()
    w.update(0, KEY, 3000, 0, 0, TIMEOUT)
    for t in range(1, 60):  # 60 s driving away from the goal at 100 mm/s
        assert w.update(t * S, KEY, 3000 + 100 * t, -100 * t, 0, TIMEOUT) is None
    assert w.count == 0


def test_the_stall_after_a_warned_detour_is_no_longer_silent():
    """What the robot did before: ProgressWatch warns once, when the distance finds no new minimum
    for 10 s, which a detour away from the goal triggers while the robot still drives; its later
    stall farther out never beats that minimum, so it is never reported again (DRIVING for good)."""
    old, new = ProgressWatch(), StallWatch()
    texts, why = [], []
    t = 0
    for dist, x in [(3000 - 100 * i, 100 * i) for i in range(10)] + [(2100 + 100 * i, 900 - 100 * i) for i in range(25)]:
        t += S  # approach to 2100 mm, then a detour that leads away from the goal, still moving
        texts.append(old.update(t, KEY[0], dist))
        why.append(new.update(t, KEY, dist, x, 0, TIMEOUT))
    assert [s for s in texts if s] == ["no progress for 10 s, 3000 mm to go"]  # warned while it drove
    assert not any(why)
    for _ in range(600):  # then it stands still for 10 minutes
        t += S
        texts.append(old.update(t, KEY[0], 4500))
        new.note(False, True, (0, 0))
        why.append(new.update(t, KEY, 4500, -1500, 0, TIMEOUT))
    assert len([s for s in texts if s]) == 1  # the old watch: silent
    assert [w for w in why if w] == ["blocked ahead"] * 30  # every NAV_STALL_S (the controller holds at the first)


def test_the_reason_is_what_the_robot_knows():
    def stalled(commanded: bool, blocked: bool, turning: bool) -> str | None:
        w = StallWatch()
        w.update(0, KEY, 3000, 0, 0, TIMEOUT)
        for i in range(400):
            w.note(commanded, blocked, (i, -i) if turning else (7, 7))
        return w.update(TIMEOUT, KEY, 3000, 0, 0, TIMEOUT)

    assert stalled(True, False, False) == "wheels not moving"  # commanded, the encoders still
    assert stalled(True, True, True) == "blocked ahead"  # turning in place, the straight part held
    assert stalled(False, True, False) == "blocked ahead"  # nothing sent, a reading in the way
    assert stalled(True, False, True) == "no progress"  # turning on the spot with the way open
    assert stalled(False, False, False) == "no progress"


def test_the_key_restarts_the_watch_and_zero_switches_it_off():
    w = StallWatch()
    w.update(0, KEY, 3000, 0, 0, TIMEOUT)
    assert w.update(15 * S, KEY, 3000, 0, 0, TIMEOUT) is None
    assert w.update(16 * S, ((1, 1), 0), 3000, 0, 0, TIMEOUT) is None  # a new goal
    assert w.update(35 * S, ((1, 1), 0), 3000, 0, 0, TIMEOUT) is None
    assert w.update(36 * S, ((1, 1), 0), 3000, 0, 0, TIMEOUT) == "no progress"
    off = StallWatch()
    off.update(0, KEY, 3000, 0, 0, 0)
    assert off.update(3600 * S, KEY, 3000, 0, 0, 0) is None
    assert STALL_MOVE_MM > 2 * 50  # moving is more than the odometry's jitter on a stop


def _drive(ctrl: Controller, rig: Rig, goal: tuple[int, int], ticks: int, resend_every: int = 0) -> list:
    rig.tick()
    assert ctrl.arm() == (True, "")
    assert ctrl.go_to(*goal) == (True, "")
    ctrl.drain_events()
    events = []
    for i in range(ticks):
        rig.tick()
        if resend_every and i % resend_every == 0 and ctrl.state == CtrlState.DRIVING:
            assert ctrl.set_goal(*goal) == (True, "")  # a GCS streaming its setpoint, as PX4's offboard wants
        events += ctrl.drain_events()
    return events


def test_a_policy_turning_on_the_spot_is_held_even_with_its_goal_sent_again_and_again():
    """ProgressWatch restarts with every goal (`_start_driving`): a goal sent again every 0.5 s kept it
    quiet for good. The stall watch keys on the goal and when the drive began."""
    cfg = VehicleConfig()
    period = cfg.control_period_us
    for resend in (0, 10):
        ctrl = Controller(cfg, _spinning_policy(), start_pose_mm=(250, 250, 0))
        rig = Rig(ctrl, Kinematic(250, 250, 0))
        events = _drive(ctrl, rig, (5000, 250), cfg.nav_stall_s * S // period + 2, resend)
        stalls = [e for e in events if e.kind == "stall"]
        assert [e.text for e in stalls] == ["stalled: no progress, 4750 mm to go"], [e.text for e in events]
        assert stalls[0].severity == 4  # MAV_SEVERITY_WARNING
        assert ctrl.state == CtrlState.HOLD and ctrl.mode == Mode.HOLD and ctrl.goal is None
        assert ctrl.transitions[-1].cause == "stalled: no progress"
        assert ctrl.stall.count == 1
        warned = [e.text for e in events if e.text.startswith("no progress")]
        assert len(warned) == (0 if resend else 1)  # the old warning: silent with the goal sent again


class _StuckWheels(Kinematic):
    """The motors are commanded but the wheels do not turn (a jammed gearbox; the driver reports no error)."""

    def step(self, left: float, right: float, dt_s: float) -> None:
        pass


def test_wheels_commanded_that_do_not_turn_are_named():
    cfg = VehicleConfig(nav_stall_s=5)
    ctrl = Controller(cfg, sector_seek_policy(), start_pose_mm=(250, 250, 0))
    rig = Rig(ctrl, _StuckWheels(250, 250, 0))
    events = _drive(ctrl, rig, (5000, 250), 5 * S // cfg.control_period_us + 2)
    assert [e.text for e in events if e.kind == "stall"] == ["stalled: wheels not moving, 4750 mm to go"]
    assert ctrl.state == CtrlState.HOLD and ctrl.mode == Mode.HOLD
    assert rig.commands[-1] is None or (rig.commands[-1].left_mm_s, rig.commands[-1].right_mm_s) == (0, 0)


def test_nav_stall_s_zero_drives_on():
    cfg = VehicleConfig(nav_stall_s=0)
    ctrl = Controller(cfg, _spinning_policy(), start_pose_mm=(250, 250, 0))
    rig = Rig(ctrl, Kinematic(250, 250, 0))
    events = _drive(ctrl, rig, (5000, 250), 2 * NO_PROGRESS_US * 4 // cfg.control_period_us)
    assert not [e for e in events if e.kind == "stall"] and ctrl.state == CtrlState.DRIVING


def test_robot_stats_json_counts_stalls(tmp_path):
    import json

    from firmware_py import cli

    stats = tmp_path / "s.json"
    assert cli.main(["--can", "virtual:cli-stalls", "--duration", "0.2", "--stats-json", str(stats), "-q"]) == 0
    assert json.loads(stats.read_text())["stalls"] == 0
