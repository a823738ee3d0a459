"""The controller's progress watch (firmware_py/control/progress.py): a
STATUSTEXT-bound warning, once per goal, when the robot stops getting
closer to its goal (the way is blocked by something the map does not show)."""

from __future__ import annotations

from array import array

from firmware_py.control.controller import Controller
from firmware_py.control.progress import MIN_GAIN_MM, NO_PROGRESS_US, ProgressWatch
from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.policy import dump_policy, load_policy
from firmware_py.vehicle import CtrlState, VehicleConfig
from tests.support.controller_rig import (
    SECTOR_TRAINING_MAP,
    TURN_LEFT,
    Kinematic,
    Rig,
    sector_seek_policy,
)


def test_watch_fires_once_per_stalled_goal_and_rearms():
    w = ProgressWatch(timeout_us=1_000_000)
    g = (1000, 0)
    assert w.update(0, g, 3000) is None
    assert w.update(500_000, g, 2990) is None  # within MIN_GAIN_MM: not progress
    text = w.update(1_000_000, g, 2990)
    assert text == "no progress for 1 s, 2990 mm to go"
    assert w.update(5_000_000, g, 2990) is None  # once
    assert w.update(5_100_000, g, 2990 - MIN_GAIN_MM - 1) is None  # progress re-arms
    assert w.update(6_100_000, g, 2900) is not None
    assert w.update(6_200_000, (0, 0), 5000) is None  # a new goal starts afresh
    assert w.update(7_100_000, (0, 0), 5000) is None
    assert w.update(7_200_000, (0, 0), 5000) is not None


def _spinning_policy():
    """Turns left in every state: never gets closer to a goal that is not behind it."""
    enc = SectorEncoder()
    vals = array("b")
    for _ in range(enc.n_states):
        vals.extend(100 if i == TURN_LEFT else 0 for i in range(enc.n_actions))
    return load_policy(dump_policy(enc, vals, "int8", 0.01, map_geometry=SECTOR_TRAINING_MAP))


def test_controller_warns_when_the_policy_stalls_and_not_when_it_drives():
    for policy, stalls in ((_spinning_policy(), True), (sector_seek_policy(), False)):
        ctrl = Controller(VehicleConfig(), policy, start_pose_mm=(250, 250, 0))
        rig = Rig(ctrl, Kinematic(250, 250, 0))
        rig.tick()
        assert ctrl.arm() == (True, "")
        assert ctrl.go_to(5000, 250) == (True, "")
        ctrl.drain_events()
        period = VehicleConfig().control_period_us
        texts = []
        for _ in range(NO_PROGRESS_US // period + 20):
            rig.tick()
            texts += [e.text for e in ctrl.drain_events() if e.kind == "info"]
        warned = [t for t in texts if t.startswith("no progress")]
        if stalls:
            assert len(warned) == 1 and ctrl.state == CtrlState.DRIVING, texts
        else:
            assert warned == [], texts


def test_a_replaced_mission_starting_at_the_stalled_waypoint_is_watched_again():
    """A mission re-planned around an obstacle may start with the waypoint the robot stalled at:
    the watch restarts with every drive, so the second stall is reported too."""
    ctrl = Controller(VehicleConfig(), _spinning_policy(), start_pose_mm=(250, 250, 0))
    rig = Rig(ctrl, Kinematic(250, 250, 0))
    rig.tick()
    assert ctrl.arm() == (True, "")
    period = VehicleConfig().control_period_us
    warned = []
    for _ in range(2):
        assert ctrl.set_mission([(5000, 250)]) == (True, "")  # the same first waypoint both times
        ok, why = ctrl.start_mission()
        assert ok, why
        for _ in range(NO_PROGRESS_US // period + 20):
            rig.tick()
            warned += [e.text for e in ctrl.drain_events() if e.kind == "info" and "no progress" in e.text]
    assert len(warned) == 2, warned
