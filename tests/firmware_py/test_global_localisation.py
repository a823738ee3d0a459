"""Global localisation: the grid-scored first update, the convergence test
(a dominant cluster several updates in a row) and the exploration's
steering (the seeded HIL run: tests/hil/test_global_localisation_hil.py)."""

import math

import pytest

from firmware_py import robot_spec
from firmware_py.control.localiser import Localiser, LocaliserConfig
from firmware_py.mapdata import grid_from_rows
from tests.support.localiser_ref import log_likelihood

ROWS = ["......", ".@@...", "...@..", "......"]


def test_seed_scores_are_the_sensor_model_at_each_grid_pose():
    """Every candidate (position, heading index j) scores the readings as the
    reference model does at heading j * 2 pi / 48 (readings below 100 mm
    carry no negative-information probe, so the two compare). The sensors'
    angles and cone edges are whole mrad (785 for pi / 4, 131 for 2 pi / 48),
    so an end point exactly on a raster square's edge (the candidates sit on
    a 100 mm grid, the raster is 25 mm) may fall on either side: such cases
    differ by one neighbouring square's value, the rest agree exactly."""
    cfg = LocaliserConfig(seed=1, seed_positions_per_tick=7)
    loc = Localiser(grid_from_rows(ROWS, 500), cfg)
    ranges = [60, 90, 30, 0, 80, 0, 100, 45]
    status = [robot_spec.RANGE_VALID] * 8
    status[3] = status[5] = robot_spec.RANGE_INVALID
    loc.init_global()
    seeding = loc._seed
    assert seeding is not None
    cells = loc._candidate_cells()
    ticks = 0
    while loc._seed is not None:
        loc.tick((0, 0, 0), ranges, status)
        ticks += 1
    assert ticks == math.ceil(len(cells) / 7)  # a share of the candidates per tick
    nh = cfg.seed_headings
    mg = loc.field.margin
    diffs = []
    for ci, (x, y) in enumerate(cells):
        for j in range(nh):
            want = log_likelihood(loc, x - mg, y - mg, j * 2 * math.pi / nh, ranges, status) / cfg.beam_weight
            diffs.append(abs(seeding.scores[ci * nh + j] - want))
    exact = sum(d < 1e-6 for d in diffs)
    assert exact >= 0.75 * len(diffs)
    assert sum(diffs) / len(diffs) < 0.02
    assert len(loc.xs) == cfg.global_particles and loc.global_mode


def test_seeding_draws_particles_near_the_pose_the_readings_fit():
    """Readings taken at a wall corner of an asymmetric map: the particles
    drawn from the grid's scores gather where those readings fit, many times
    more than uniform particles do (one set of readings, softened by the
    global beam weight: other corners keep particles too)."""
    grid = grid_from_rows(["@@@@@@", "@....@", "@.@..@", "@....@", "@@@@@@"], 500)
    loc = Localiser(grid, LocaliserConfig(seed=2))
    # at (750, 1750) heading east (cell (1, 1), north-west corner of the free space): the reading of each
    # sensor from a plain ray march over the grid
    ranges, status = [], []
    for a in robot_spec.SENSOR_ANGLES_MRAD:
        c, s = math.cos(a / 1000), math.sin(a / 1000)
        d = robot_spec.SENSOR_MOUNT_RADIUS_MM
        while not grid.occupied(math.floor((750 + d * c) / 500), grid.height - 1 - math.floor((1750 + d * s) / 500)):
            d += 1
        r = d - robot_spec.SENSOR_MOUNT_RADIUS_MM
        ranges.append(r)
        status.append(robot_spec.RANGE_VALID if r <= robot_spec.RANGE_MAX_MM else robot_spec.RANGE_TOO_FAR)
    def near() -> int:
        return sum(math.hypot(x - 750, y - 1750) < 200 and abs(t) < 0.3
                   for x, y, t in zip(loc.xs, loc.ys, loc.ths, strict=True))

    loc.init_global()
    uniform = near()  # the baseline: particles uniform over free space, as before the seeding
    while loc._seed is not None:
        loc.tick((0, 0, 0), ranges, status)
    assert near() >= 5 * max(uniform, 5)


def test_converged_only_after_the_cluster_dominates_several_updates():
    grid = grid_from_rows(ROWS, 500)
    cfg = LocaliserConfig(seed=3, converge_updates=3, global_particles=200)
    loc = Localiser(grid, cfg)
    loc.init_global()
    loc._seed = None  # skip the seeding: every particle at one pose, a single dominant cluster
    loc.xs, loc.ys, loc.ths = [1250.0] * 200, [1250.0] * 200, [0.0] * 200
    ranges, status = [0] * 8, [robot_spec.RANGE_INVALID] * 8
    seen = []
    for _ in range(3):
        loc._force_update = True
        while True:
            before = loc.updates
            loc.tick((0, 0, 0), ranges, status)
            if loc.updates != before:
                break
        seen.append(loc.localised)
    assert seen == [False, False, True] and not loc.global_mode


@pytest.mark.parametrize(("left", "right", "want"), [
    (200, 200, (250, 250)),  # centred in a 500 mm corridor: the diagonals read ~200 mm each: straight on
    (300, 200, (220, 280)),  # more room on the left: steer left (right wheel faster), 0.3 (mm/s)/mm
    (2000, 130, (170, 330)),  # capped at 80 mm/s
    (70, 900, (-160, 160)),  # a diagonal within 80 mm: turn in place
])
def test_exploration_drives_through_corridors_and_steers_to_the_room(left, right, want):
    from firmware_py.control.controller import Controller
    from firmware_py.control.io import Inputs
    from firmware_py.policy import load_policy
    from firmware_py.shipped_policies import shipped_policy
    from firmware_py.vehicle import CtrlState

    ctrl = Controller(policy=load_policy(shipped_policy("sector")), start_pose_mm=(1250, 1250, 0))
    ok, why = ctrl.localise_global(explore=True)
    assert ok, why
    ctrl.armed, ctrl.state = True, CtrlState.HOLD  # arming itself is covered by the controller tests
    inp = Inputs()
    inp.ranges_mm = [900, left, 900, 900, 900, 900, 900, right]
    inp.range_status = [robot_spec.RANGE_VALID] * 8
    ctrl._explore(inp, 1000)
    assert ctrl.watchdog._setpoint == want


def _exploring_rig():
    from firmware_py.control.controller import Controller
    from firmware_py.policy import load_policy
    from firmware_py.shipped_policies import shipped_policy
    from tests.support.controller_rig import Kinematic, Rig

    ctrl = Controller(policy=load_policy(shipped_policy("sector")), start_pose_mm=(1250, 1250, 0))
    rig = Rig(ctrl, Kinematic(1250, 1250, 0.0))
    rig.tick()
    assert ctrl.arm() == (True, "")
    assert ctrl.localise_global(explore=True)[0]
    rig.tick()
    assert ctrl.exploration.running and rig.last_motor.left_mm_s != 0  # wandering
    return ctrl, rig


@pytest.mark.parametrize("stop", ["mode hold", "mode guided", "failsafe none", "failsafe hold", "disarm"])
def test_hold_failsafe_and_disarm_end_the_exploration_at_the_next_tick(stop):
    """Hold always stops: a SET_MODE (Hold included, though the robot is already in Hold), a GCS
    failsafe whatever its action, or disarming ends the wander; the very next tick commands zero."""
    from firmware_py.vehicle import FailsafeAction, Mode

    ctrl, rig = _exploring_rig()
    if stop.startswith("mode"):
        assert ctrl.set_mode(Mode.HOLD if stop == "mode hold" else Mode.GUIDED)[0]
    elif stop.startswith("failsafe"):
        ctrl.cfg.gcs_failsafe_action = FailsafeAction.NONE if stop == "failsafe none" else FailsafeAction.HOLD
        ctrl.set_failsafe(True)
    else:
        assert ctrl.disarm() == (True, "")
    rig.tick()
    assert not ctrl.exploration.running
    assert rig.commands[-1] is None or (rig.commands[-1].left_mm_s, rig.commands[-1].right_mm_s) == (0, 0)
    for _ in range(5):  # and it stays stopped
        rig.tick()
        assert rig.commands[-1] is None or (rig.commands[-1].left_mm_s, rig.commands[-1].right_mm_s) == (0, 0)
    assert any("exploration stopped" in e.text for e in ctrl.drain_events())


def test_asking_again_does_not_extend_the_exploration():
    ctrl, rig = _exploring_rig()
    until = ctrl.exploration.until_us
    for _ in range(10):
        rig.tick()
    ok, why = ctrl.localise_global(explore=True)
    assert ok and why.startswith("already exploring") and ctrl.exploration.until_us == until
