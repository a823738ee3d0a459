"""`qnav bench nav` with a sector policy that steers on the robot's local
planner: the twin rolls it out with the robot's own planner code and gets
round discs the plain table stalls at; its `.qtab` carries the map and the
planner parameters; HIL drives it through the robot's controller."""

from __future__ import annotations

import math

from firmware_py import robot_spec
from firmware_py.kinds.sector.config import LocalPlannerConfig
from firmware_py.policy import load_policy
from firmware_py.shipped_policies import shipped_policy
from ground_station.lab.nav import controllers as nc
from ground_station.lab.nav.episodes import run_hil, run_twin
from ground_station.lab.nav.scenario import Episode, episodes
from ground_station.maps import load_map

RADIUS_MM = float(robot_spec.ROBOT_RADIUS_MM)


def _seg_hits_disc(ax: float, ay: float, bx: float, by: float, cx: float, cy: float, r: float) -> bool:
    dx, dy = bx - ax, by - ay
    l2 = dx * dx + dy * dy
    t = 0.0 if l2 == 0 else max(0.0, min(1.0, ((cx - ax) * dx + (cy - ay) * dy) / l2))
    return math.hypot(ax + t * dx - cx, ay + t * dy - cy) < r


def blocked_segments(ep: Episode) -> int:
    """Planned segments (start -> waypoints) that a disc grown by the robot's radius crosses."""
    pts = [ep.start[:2], *ep.waypoints]
    return sum(any(_seg_hits_disc(*a, *b, cx, cy, r + RADIUS_MM) for cx, cy, r in ep.discs)
               for a, b in zip(pts[:-1], pts[1:], strict=True))


def _controllers() -> tuple[nc.NavController, nc.NavController, nc.NavController]:
    pol = load_policy(str(shipped_policy("sector")))
    assert pol.kind_config == LocalPlannerConfig()  # the shipped sector policy steers on the planner
    planned, seek_local = nc.standard_controllers(pol, ("learnt", "seek_local"))
    plain = nc.NavController("learnt", planned.encoder, planned.q, "path")  # the same table without it
    return plain, planned, seek_local


def test_planner_gets_round_discs_the_plain_table_stalls_at():
    gm = load_map("paper10")
    eps = [e for e in episodes(gm, 60, 0, 3, 0) if blocked_segments(e)][:12]  # a disc across the plan
    assert len(eps) == 12
    plain, planned, seek_local = _controllers()
    assert seek_local.local == LocalPlannerConfig() and seek_local.encoder == plain.encoder
    # the VFH follower on the same planner: the VFH table, the planner's parameters
    [vfh] = nc.standard_controllers(load_policy(shipped_policy("sector")), ("vfh_local",))
    assert vfh.local == LocalPlannerConfig() and (vfh.q == nc.vfh_table(plain.encoder)).all()
    p = sum(r["success"] for r in run_twin(eps, {"paper10": gm}, plain))
    lp = sum(r["success"] for r in run_twin(eps, {"paper10": gm}, planned))
    assert lp >= p + 4, (p, lp)


def test_exported_policy_carries_map_and_planner_and_runs_in_hil():
    gm = load_map("paper10")
    _, planned, _ = _controllers()
    pol = planned.policy("paper10")
    assert pol.kind == "sector" and pol.kind_config == LocalPlannerConfig()
    assert pol.map_grid is not None and (pol.map_grid.width, pol.map_grid.height) == (10, 10)
    again = nc.standard_controllers(pol, ("learnt",))[0]
    assert again.local == LocalPlannerConfig()
    eps = [e for e in episodes(gm, 60, 0, 3, 0) if blocked_segments(e)][:3]  # a disc across the plan
    rows = run_hil(eps, {"paper10": gm}, planned)  # the robot's controller runs the planner on the pymunk plant
    for r in rows:
        assert r["success"] == (r["result"] == "reached" and r["contacts"] == 0)
    assert sum(r["success"] for r in rows) >= 2, rows
