"""No silent stall (issue 44 item 5), reproduced on the lockstep rig: the shipped cell policy drives
along paper10's bottom row at a disc its map does not show; the collision monitor stops it short
of the disc and the policy has nothing else to do. Before, the robot sat in DRIVING with zero
wheel commands until something else ended it (one "no progress" warning at 10 s, then nothing).
Now the robot's MAVLink node (the real MavNode core, polled after every tick as qnav-robot's
link thread does) sends a STATUSTEXT warning naming why within NAV_STALL_S + one period of the
robot standing still, the robot holds, it is counted, and the monitor's model shows the count."""

from __future__ import annotations

import math

import pytest

from firmware_py import robot_spec
from firmware_py.mavlink.dialect import mavlink2
from firmware_py.policy import load_policy
from firmware_py.shipped_policies import shipped_policy
from firmware_py.vehicle import CtrlState, Mode
from ground_station.lab.rigs.lockstep import LockstepRig
from ground_station.maps import load_map
from ground_station.monitor.model import VehicleView
from sim_bridge.obstacles import ObstacleLayer

PERIOD_US = robot_spec.CONTROL_PERIOD_US
START = (3.25, 0.25, math.pi)  # paper10 cell (6, 9), facing west along the free bottom row
MISSION = [(250, 250), (4750, 1250)]  # the cell policy's targets (0, 9) and (9, 7)
DISC = (1750.0, 250.0, 200.0)  # on the row, not on the robot's map


class _Link:
    """The robot's MAVLink node over the rig's controller, polled after every tick; every frame it
    sends goes on the wire into a VehicleView, as `qnav monitor` reads them."""

    def __init__(self, rig: LockstepRig, stall_s: int | None) -> None:
        from firmware_py.mavlink.node import MavNode
        from firmware_py.mavlink.params import ParamStore
        from firmware_py.mavlink.signing import Signing

        self.node = MavNode(rig.ctrl, ParamStore(None), Signing(None))
        self.node.boot(0)
        if stall_s is not None:
            ok, why = self.node.params.set("NAV_STALL_S", stall_s)
            assert ok, why
            self.node._apply_params(reboot=False)
        self.rx = mavlink2.MAVLink(None)
        self.view = VehicleView()
        self.texts: list[tuple[int, int, str]] = []  # (robot time us, severity, text)
        self.clock = rig.node.clock
        rig.node.after_tick.append(self.poll)

    def poll(self, _out: object) -> None:
        now = self.clock.now_us()
        for msg in self.node.tick(now):
            for got in self.rx.parse_buffer(bytes(msg.pack(self.node.mav))) or []:
                self.view.update(got, now / 1e6)
                if got.get_type() == "STATUSTEXT":
                    self.texts.append((now, got.severity, got.text))


def _run(stall_s: int | None, until_s: float):
    gm = load_map("paper10")
    with LockstepRig(gm.occ, load_policy(shipped_policy("paper10_cell")), START, MISSION, seed=0) as rig:
        rig.plant.obstacles = ObstacleLayer(rig.plant.world, [DISC], [])
        link = _Link(rig, stall_s)
        while rig.plant.time_us < until_s * 1e6:  # on after the GoalRunner is done: held for good
            rig.tick()
        return rig, link


def _last_progress(rig: LockstepRig, t_us: int) -> int:
    """When the robot last made progress before t_us, by its own pose (what it can know): the
    distance to the goal beat its best by MIN_GAIN_MM, or the pose moved STALL_MOVE_MM from where
    it was at the last such moment."""
    from firmware_py.control.progress import MIN_GAIN_MM, STALL_MOVE_MM

    gx, gy = MISSION[0]
    best, at, since = math.inf, (0, 0), 0
    for t, _tx, _ty, x, y, _ox, _oy in rig.poses:
        if t > t_us:
            break
        d = math.hypot(x - gx, y - gy)
        if d < best - MIN_GAIN_MM or math.hypot(x - at[0], y - at[1]) >= STALL_MOVE_MM:
            best, at, since = min(best, d), (x, y), t
    return since


@pytest.mark.parametrize("stall_s", [None, 8])  # the default (20 s), and one set over MAVLink
def test_a_robot_stopped_short_of_an_unmapped_disc_says_so_and_holds(stall_s):
    limit_s = 20 if stall_s is None else stall_s
    rig, link = _run(stall_s, until_s=limit_s + 30)
    stalls = [(t, sev, text) for t, sev, text in link.texts if "stalled" in text and "->" not in text]
    assert len(stalls) == 1, (link.texts, rig.ctrl.state.name)
    t_us, severity, text = stalls[0]
    assert text.startswith("item 0: stalled: blocked ahead, ") and text.endswith(" mm to go"), text
    assert severity == mavlink2.MAV_SEVERITY_WARNING
    assert any("DRIVING->HOLD: stalled: blocked ahead" in tx for _, _, tx in link.texts)
    last = _last_progress(rig, t_us)
    assert limit_s * 1_000_000 <= t_us - last <= limit_s * 1_000_000 + PERIOD_US, (last, t_us)
    # held: mode Hold, no goal, wheels stopped, the mission item still current for mode Auto to retry
    assert rig.runner.result == "stopped: stalled: blocked ahead"
    assert rig.ctrl.state == CtrlState.HOLD and rig.ctrl.mode == Mode.HOLD and rig.ctrl.goal is None
    assert rig.ctrl.route.seq == 0
    assert rig.commands[-1][0] > t_us + 10_000_000  # ticked on for a while after it
    assert all((left, right) == (0, 0) for t, left, right, _ in rig.commands if t > t_us)
    assert rig.plant.world.contact_events == 0
    # counted (robot_stats.json `stalls`) and shown by the monitor's status line
    assert rig.ctrl.stall.count == 1
    assert link.view.stalls == 1 and "stalls=1" in link.view.status_line(t_us / 1e6)


def test_nav_stall_s_zero_leaves_the_drive_to_the_operator():
    rig, link = _run(0, until_s=35)
    assert rig.ctrl.state == CtrlState.DRIVING and rig.ctrl.stall.count == 0
    assert not [tx for _, _, tx in link.texts if "stalled" in tx]
