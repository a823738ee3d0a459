"""`qnav policy attach-map`: the training map's cells into a policy file."""

import numpy as np

from firmware_py.kinds.sector.encoder import SectorEncoder
from firmware_py.policy import MapGeometry, load_policy
from ground_station.cli import main
from ground_station.learn.export import policy_bytes, quantise

PAPER10 = MapGeometry(500, 10, 10)


def _sector(path, geometry=PAPER10, meta=None):
    q = quantise(np.random.default_rng(1).normal(size=(SectorEncoder().n_states, 4)))
    path.write_bytes(policy_bytes(q, SectorEncoder(), map_geometry=geometry, metadata=meta or {"map": "paper10"}))
    return path


def test_attach_map_adds_the_grid_and_keeps_the_table(tmp_path, capsys):
    f = _sector(tmp_path / "p.qtab")
    before = load_policy(f)
    assert before.map_grid is None
    assert main(["policy", "attach-map", str(f)]) == 0  # the map named in the metadata
    assert "map_grid=25/100 occupied" in capsys.readouterr().out
    after = load_policy(f)
    assert after.map_grid is not None and after.map_grid.rows()[1] == ".@@@...@@."
    assert (after.policy_id, after.created, bytes(after.table)) == (before.policy_id, before.created,
                                                                     bytes(before.table))
    assert main(["policy", "inspect", str(f)]) == 0
    assert "map_grid=25/100 occupied" in capsys.readouterr().out


def test_attach_map_refuses_a_map_of_another_size_and_leaves_the_file(tmp_path, capsys):
    f = _sector(tmp_path / "p.qtab", MapGeometry(500, 12, 8))
    data = f.read_bytes()
    assert main(["policy", "attach-map", str(f), "--map", "paper10"]) == 2
    err = capsys.readouterr().err.strip()
    assert "map paper10 is 10x10 cells, the policy was trained on 12x8" in err and "\n" not in err
    assert f.read_bytes() == data
    g = _sector(tmp_path / "q.qtab", meta={"note": "no map named"})
    assert main(["policy", "attach-map", str(g)]) == 2
    assert "names no training map in its metadata; pass --map" in capsys.readouterr().err
