"""`qnav bench nav` with a `sector-unmapped` policy: the exported `.qtab`
carries the map the detour needs, the baselines run on its go rows' encoder,
and the HIL loop drives it through the robot's own controller on the
lockstep rig (pymunk plant with the discs and movers)."""

from __future__ import annotations

import numpy as np

from firmware_py.encoders import SectorEncoder, best_action
from firmware_py.policy import load_policy
from firmware_py.shipped_policies import shipped_policy
from firmware_py.unmapped import UnmappedSectorEncoder
from ground_station.learn.sector.unmapped import hand_detour_table
from ground_station.maps import load_map
from ground_station.nav import controllers as nc
from ground_station.nav.episodes import run_hil, run_twin
from ground_station.nav.scenario import episodes

ENC = UnmappedSectorEncoder()


def _hand() -> nc.NavController:
    pol = load_policy(str(shipped_policy("sector")))
    return nc.NavController("learnt", ENC, hand_detour_table(nc.policy_table(pol) * pol.scale, ENC), "path")


def test_exported_policy_carries_the_map_and_the_baselines_use_the_go_rows():
    ctrl = _hand()
    pol = ctrl.policy("paper10")
    assert pol.kind == "sector-unmapped" and pol.encoder == ENC and pol.map_grid is not None
    assert (pol.map_grid.width, pol.map_grid.height) == (10, 10)
    for s in range(0, pol.n_states, 97):  # int8 with per-state scales keeps the greedy choice
        assert best_action(pol.row(s)) == int(np.argmax(ctrl.q[s]))
    learnt, seek, vfh = nc.standard_controllers(pol, ("learnt", "seek", "vfh"))
    assert learnt.encoder == ENC
    assert seek.encoder == vfh.encoder == SectorEncoder(15, (0, 1, 7), (100, 400))


def test_hil_runs_the_detour_policy_on_the_lockstep_rig():
    gm = load_map("paper10")
    eps = episodes(gm, 2, 5, 3, 1)
    ctrl = _hand()
    rows = run_hil(eps, {"paper10": gm}, ctrl)
    twin = run_twin(eps, {"paper10": gm}, ctrl)
    assert len(rows) == len(twin) == 2
    for r in rows:
        assert r["outcome"] in ("success", "collision", "timeout", "stopped")
        assert r["success"] == (r["result"] == "reached" and r["contacts"] == 0)
        assert r["time_s"] > 0
