"""Maps: MovingAI parsing and its one-line errors, sidecar targets, BFS and
octile distances on hand-made maps, seeded generators, built-in maps."""

import math
from collections import deque

import numpy as np
import pytest

from ground_station.maps import (
    GridMap,
    MapError,
    bfs_distances,
    builtin_names,
    dump_map,
    load_map,
    maze_map,
    octile_distances,
    parse_map,
    random_map,
    read_map,
    read_scen,
    rooms_map,
    trap_map,
    write_map,
)

GOOD = "type octile\nheight 3\nwidth 4\nmap\n....\n.@T.\nGS..\n"


def test_parse_good_map_and_row0_is_first_text_row():
    gm = parse_map(GOOD, "good")
    assert (gm.height, gm.width) == (3, 4)
    assert gm.occ.dtype == bool
    assert gm.occ[1, 1] and gm.occ[1, 2] and not gm.occ[2, 0]
    assert gm.is_free(0, 2) and not gm.is_free(1, 1) and not gm.is_free(4, 0) and not gm.is_free(-1, 0)
    assert len(gm.free_cells()) == 10
    assert (1, 1) not in gm.free_cells()


def test_crlf_and_trailing_blank_lines_are_accepted():
    gm = parse_map(GOOD.replace("\n", "\r\n") + "\r\n\r\n", "crlf")
    assert gm.occ.sum() == 2


@pytest.mark.parametrize("text, fragment", [
    ("tipe octile\nheight 3\nwidth 4\nmap\n", "bad header"),
    ("type octile\nheight x\nwidth 4\nmap\n....\n", "bad header"),
    ("type octile\nheight 3\nwidth 4\nmop\n", "bad header"),
    ("type octile\nheight 3\n", "bad header"),
    ("type octile\nheight 3\nwidth 4\nmap\n....\n....\n", "wrong row count"),
    ("type octile\nheight 2\nwidth 4\nmap\n....\n...\n", "wrong width"),
    ("type octile\nheight 2\nwidth 4\nmap\n....\n..x.\n", "unknown character 'x'"),
])
def test_malformed_maps_raise_one_line_map_error(text, fragment):
    with pytest.raises(MapError) as exc:
        parse_map(text, "bad.map")
    msg = str(exc.value)
    assert fragment in msg and "bad.map" in msg
    assert "\n" not in msg
    assert isinstance(exc.value, ValueError)


def test_unknown_character_error_names_line_and_column():
    with pytest.raises(MapError, match=r"bad.map:6: unknown character 'x' at column 2"):
        parse_map("type octile\nheight 2\nwidth 4\nmap\n....\n..x.\n", "bad.map")


def test_write_read_round_trip_with_targets_sidecar(tmp_path):
    gm = GridMap("t", parse_map(GOOD).occ, {"B": (3, 0), "A": (0, 2)})
    path = tmp_path / "sub" / "t.map"
    write_map(path, gm)
    assert (tmp_path / "sub" / "t.targets.json").exists()
    back = read_map(path)
    assert np.array_equal(back.occ, gm.occ)
    assert list(back.targets.items()) == [("B", (3, 0)), ("A", (0, 2))]  # order is the goal order
    assert dump_map(back) == dump_map(gm)
    assert not list((tmp_path / "sub").glob("*.tmp"))


def test_target_on_obstacle_or_outside_is_rejected(tmp_path):
    occ = parse_map(GOOD).occ
    # issue 30 finding 7: a wall and a cell off the map are named as such
    with pytest.raises(MapError, match="target X at \\(1,1\\) is a wall of map t"):
        GridMap("t", occ, {"X": (1, 1)})
    h, w = occ.shape
    with pytest.raises(MapError, match=f"target X at \\(9,0\\) is outside the {w}x{h} map t"):
        GridMap("t", occ, {"X": (9, 0)})
    (tmp_path / "m.map").write_text(GOOD)
    (tmp_path / "m.targets.json").write_text('{"A": [0]}')
    with pytest.raises(MapError, match="must be \\[col, row\\]"):
        read_map(tmp_path / "m.map")


def test_load_map_errors_are_one_line():
    with pytest.raises(MapError, match="unknown map 'nosuchmap'"):
        load_map("nosuchmap")
    with pytest.raises(MapError, match="no such map file"):
        load_map("/nonexistent/dir/x.map")


def test_paper10_is_builtin_with_four_reachable_targets():
    assert "paper10" in builtin_names()
    gm = load_map("paper10")
    assert (gm.height, gm.width) == (10, 10)
    assert list(gm.targets) == ["A", "B", "C", "D"]
    assert gm.occ.sum() > 10
    free = ~gm.occ
    for c, r in gm.targets.values():
        d = bfs_distances(gm.occ, c, r)
        assert (d[free] >= 0).all()  # every free cell reaches every target


def test_shared_benchmark_maps_load_by_name():
    for name in ("random-32-32-20", "room-32-32-4"):
        gm = load_map(name)
        assert (gm.height, gm.width) == (32, 32)


def test_bfs_hand_made_map():
    occ = parse_map("type octile\nheight 3\nwidth 4\nmap\n....\n.@@.\n...@\n").occ
    d = bfs_distances(occ, 0, 0)
    expected = np.array([[0, 1, 2, 3],
                         [1, -1, -1, 4],
                         [2, 3, 4, -1]], dtype=np.int32)
    assert d.dtype == np.int32
    assert np.array_equal(d, expected)


def test_bfs_matches_reference_bfs_on_random_maps():
    rng = np.random.default_rng(1)
    for _ in range(20):
        h, w = rng.integers(2, 12, size=2)
        occ = rng.random((h, w)) < 0.3
        gr, gc = int(rng.integers(h)), int(rng.integers(w))
        ref = np.full((h, w), -1)
        if not occ[gr, gc]:
            ref[gr, gc] = 0
            dq = deque([(gr, gc)])
            while dq:
                r, c = dq.popleft()
                for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                    nr, nc = r + dr, c + dc
                    if 0 <= nr < h and 0 <= nc < w and not occ[nr, nc] and ref[nr, nc] < 0:
                        ref[nr, nc] = ref[r, c] + 1
                        dq.append((nr, nc))
        assert np.array_equal(bfs_distances(occ, gc, gr), ref)


def test_octile_diagonals_and_no_corner_cutting():
    occ = np.zeros((3, 3), dtype=bool)
    d = octile_distances(occ, 0, 0)
    assert d[2, 2] == pytest.approx(2 * math.sqrt(2))
    assert d[1, 2] == pytest.approx(1 + math.sqrt(2))
    # an obstacle at (col 1, row 0) forbids the diagonal (0,0)->(1,1) that would cut its corner
    occ[0, 1] = True
    d = octile_distances(occ, 0, 0)
    assert d[1, 1] == pytest.approx(2.0)
    assert d[0, 1] == math.inf
    # walled-off goal region
    occ = np.array([[0, 1, 0], [1, 0, 0], [0, 0, 0]], dtype=bool)
    d = octile_distances(occ, 0, 0)
    assert d[0, 0] == 0 and np.isinf(d[1:, 1:]).all()  # diagonal through two blocked sides not allowed


def test_goal_on_obstacle_reaches_nothing_and_bad_goal_raises():
    occ = np.ones((2, 2), dtype=bool)
    assert (bfs_distances(occ, 0, 0) == -1).all()
    assert np.isinf(octile_distances(occ, 1, 1)).all()
    with pytest.raises(ValueError, match="outside"):
        bfs_distances(occ, 5, 0)


@pytest.mark.parametrize("gen", [random_map, rooms_map, trap_map, maze_map])
def test_generators_are_seeded_and_connected(gen):
    a = gen(20, 16, seed=3)
    b = gen(20, 16, seed=3)
    c = gen(20, 16, seed=4)
    assert np.array_equal(a.occ, b.occ)
    assert not np.array_equal(a.occ, c.occ)
    assert a.occ.shape == (16, 20)
    assert a.occ.any()
    free = a.free_cells()
    c0, r0 = free[0]
    d = bfs_distances(a.occ, c0, r0)
    assert (d[~a.occ] >= 0).all()


def test_generator_specs_load_by_name():
    gm = load_map("trap-16x12-s2")
    assert (gm.width, gm.height) == (16, 12)
    assert np.array_equal(gm.occ, trap_map(16, 12, seed=2).occ)


def test_read_scen(tmp_path):
    p = tmp_path / "x.scen"
    p.write_text("version 1\n0\tx.map\t4\t3\t0\t0\t3\t2\t5.00000000\n1\tx.map\t4\t3\t1\t0\t0\t2\t3\n")
    sc = read_scen(p)
    assert [s.start for s in sc] == [(0, 0), (1, 0)]
    assert sc[0].goal == (3, 2) and sc[0].optimal == 5.0 and sc[1].bucket == 1
    p.write_text("version 1\n0\tx.map\t4\n")
    with pytest.raises(MapError, match="expected 9 fields"):
        read_scen(p)


def test_reading_a_map_file_does_not_import_numba(tmp_path):
    """The sim and `qnav map upload` read map files: numba (its kernels compute distances and generate
    maps) is imported only when one of those is asked for (ground_station/maps/__init__.py)."""
    import subprocess
    import sys

    write_map(tmp_path / "m.map", parse_map(GOOD, name="m"))
    code = ("import sys; from ground_station.maps import load_map; load_map(sys.argv[1]); load_map('paper10'); "
            "a = 'numba' in sys.modules; import ground_station.maps as m; m.octile_distances; "
            "b = 'numba' in sys.modules; load_map('trap-8x8-s1'); print(a, b)\n"
            "try:\n    m.no_such_name\nexcept AttributeError as e:\n    print(e)")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "m.map")], capture_output=True, text=True,
                       timeout=60, check=False)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == ["False True", "module 'ground_station.maps' has no attribute 'no_such_name'"]
