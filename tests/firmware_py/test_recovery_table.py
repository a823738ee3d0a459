"""The recovery decisions as a table (`firmware_py.kinds.sector.decide`, issue 47): the int8 table in a
policy's metadata round-trips and bad ones are refused at load, old files load and keep the
hand-written rules, and a table's choices are what `PlannedTarget` does at the two decision events."""

from __future__ import annotations

from array import array

import pytest

from firmware_py import robot_spec
from firmware_py.background import Background
from firmware_py.kinds.sector import SectorDriver, decide
from firmware_py.kinds.sector.memory import ObstacleMemory
from firmware_py.kinds.sector.recoveries import GLOBAL, NO_ROUTE, WAIT, PlannedTarget
from firmware_py.policy import PolicyError, load_policy
from firmware_py.shipped_policies import resolve_policy_spec
from tests.firmware_py.test_replan import DOOR1, ONE_DOOR, _drive
from tests.support.localplan_rig import CFG

PERIOD = robot_spec.CONTROL_PERIOD_US


def _table(wait_action: int, round_action: int) -> decide.RecoveryTable:
    """A table choosing `wait_action` at every waiting row and `round_action` at every round row."""
    t = array("b", [0] * (decide.N_STATES * decide.N_ACTIONS))
    for s in range(decide.N_STATES):
        t[s * decide.N_ACTIONS + (wait_action if s < decide.N_WAIT else round_action)] = 100
    return decide.RecoveryTable(t, 0.01)


def test_the_table_round_trips_and_bad_ones_are_refused():
    t = _table(decide.REPLAN, decide.NO_ROUTE)
    back = decide.RecoveryTable.from_metadata(t.to_metadata())
    assert back.table == t.table and back.scale == t.scale
    assert back.choose(decide.wait_state(0, 0, 2, False)) == decide.REPLAN
    assert back.choose(decide.round_state(0, 1, False, False, False)) == decide.NO_ROUTE
    meta = t.to_metadata()
    for bad, why in (({**meta, "table": meta["table"][:-4]}, "bytes, need"), ({**meta, "version": 2}, "version"),
                     ({**meta, "scale": -1}, "scale"), ({**meta, "table": "!!"}, "base64"),
                     ({"table": meta["table"]}, "object of")):
        with pytest.raises(ValueError, match=why):
            decide.RecoveryTable.from_metadata(bad)


def test_an_invalid_column_is_never_chosen_however_large():
    t = array("b", [0] * (decide.N_STATES * decide.N_ACTIONS))
    s = decide.wait_state(3_000_000, 1, 0, True)
    t[s * decide.N_ACTIONS + decide.NO_ROUTE] = 127  # not an action of the waiting event
    assert decide.RecoveryTable(t).choose(s) == decide.WAIT  # ties to the lowest valid index


def test_old_files_load_with_the_rules_and_a_file_with_a_table_runs_it():
    from ground_station.lab.nav.controllers import with_recovery_table
    from ground_station.learn.export import with_metadata

    old = load_policy(str(resolve_policy_spec("policies:sector")))
    assert decide.META_KEY not in old.metadata
    assert SectorDriver(old, Background(threaded=False)).local[0].decisions is None  # type: ignore[index]
    data = with_recovery_table("policies:sector", _table(decide.WAIT, decide.GIVE_WAY), {"note": "test"})
    new = load_policy(data)
    got = SectorDriver(new, Background(threaded=False)).local[0].decisions  # type: ignore[index]
    assert got is not None and got.choose(decide.round_state(0, 1, True, False, True)) == decide.GIVE_WAY
    broken = {**new.metadata, decide.META_KEY: {**new.metadata[decide.META_KEY], "table": "AAAA"}}
    with pytest.raises(PolicyError, match="recovery_table.table is 3 bytes"):
        load_policy(with_metadata(new, broken))
    no_planner = {k: v for k, v in new.metadata.items() if k != "local_planner"}
    with pytest.raises(PolicyError, match="recovery_table needs the local_planner"):
        load_policy(with_metadata(new, no_planner))


def test_a_table_that_re_plans_at_once_and_gives_up_says_no_route_in_one_round():
    work = Background(threaded=False)
    pt = PlannedTarget(ONE_DOOR, CFG, work, decisions=_table(decide.REPLAN, decide.NO_ROUTE))
    rows = _drive(pt, work, ObstacleMemory(CFG), 200, seen=DOOR1)
    modes = [r[1] for r in rows]
    assert NO_ROUTE in modes and pt.global_plans == 1
    said = rows[modes.index(NO_ROUTE)][0]
    # one decision period of waiting (the rule waits 2 + 4 + 6 s and backs off twice)
    assert said <= decide.DECIDE_US + 20 * PERIOD
    waited = [r for r in rows if r[1] == WAIT]
    assert waited[-1][0] - waited[0][0] >= decide.DECIDE_US - PERIOD


def test_a_table_that_always_tries_again_is_bounded_by_the_rounds_cap():
    work = Background(threaded=False)
    pt = PlannedTarget(ONE_DOOR, CFG, work, decisions=_table(decide.REPLAN, decide.WAIT))
    rows = _drive(pt, work, ObstacleMemory(CFG), 1500, seen=DOOR1)
    modes = [r[1] for r in rows]
    assert NO_ROUTE in modes and pt.global_plans == 3 * CFG.max_rounds
    assert modes.count(GLOBAL) > 0
