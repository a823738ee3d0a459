"""The robot's clearances come from its profile's body (issue 44 step 3), not robot_spec's 150 mm: the
goal check (a goal closer to a wall than the body's radius is refused), the sector planner's refuge
(how far aside it gives way) and the local planner's body clearances."""

from __future__ import annotations

from pathlib import Path

from firmware_py.control.decision import KindPart
from firmware_py.kinds.sector import SectorDriver
from firmware_py.kinds.sector.config import LocalPlannerConfig
from firmware_py.kinds.sector.planner import REFUGE_MM, refuge_mm
from firmware_py.policy import load_policy
from firmware_py.profile import load_profile
from firmware_py.shipped_policies import shipped_policy

WIDE = Path(__file__).resolve().parents[2] / "firmware_py" / "profiles" / "wide_six.toml"


def test_a_goal_the_wide_body_does_not_fit_at_is_refused_naming_its_radius():
    pol = load_policy(shipped_policy("sector"))
    grid = pol.map_grid
    assert grid is not None
    # a free point 160 mm from the nearest wall: the built-in 150 mm body fits there, a 180 mm one does not
    x, y = next((x, y) for x in range(100, grid.width * grid.cell_mm, 10) for y in range(100, 1500, 10)
                if not grid.occupied(x // grid.cell_mm, grid.height - 1 - y // grid.cell_mm)
                and 160 <= grid.clearance_mm(x, y, 180) < 170)
    assert KindPart(pol, lockstep=True).goal_index(x, y) == (0, "")
    gi, why = KindPart(pol, lockstep=True, layout=load_profile(WIDE).layout()).goal_index(x, y)
    assert gi == -1 and why.endswith("mm from a wall (robot radius 180)"), why


def test_the_planners_refuge_and_body_clearances_follow_the_body():
    assert REFUGE_MM == refuge_mm(150) == 450 and refuge_mm(180) == 510
    built_in = LocalPlannerConfig()
    assert built_in.for_body(150) is built_in
    wide = built_in.for_body(180)
    assert (wide.wall_clear_mm, wide.obstacle_clear_mm, wide.soft_mm, wide.los_clear_mm) == (205, 220, 380, 280)
    assert wide.margin_mm == built_in.margin_mm and wide.veto_mm == built_in.veto_mm  # not the body's
    pol = load_policy(shipped_policy("sector"))
    from dataclasses import replace

    planned = replace(pol, kind_config=built_in)
    driver = SectorDriver(planned, layout=load_profile(WIDE).layout())
    assert driver.local is not None
    planner, _, _ = driver.local
    assert planner.cfg.wall_clear_mm == 205 and planner.radius_mm == 180
