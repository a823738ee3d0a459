"""`qnav map upload`: the map is the robot's (issue 32). Over MAVLink FTP to a running qnav-robot:
a sector policy takes the robot's map (localises and plans on it), a cell policy tied to paper10
refuses another map naming both, a malformed file is refused with the reason and the old map kept,
and the robot boots the map it was last given."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from ground_station.subprocs import free_udp_port, stop_process

BIN = Path(sys.executable).parent


def _robot(storage: Path, policy: str, port: int, stats: Path) -> subprocess.Popen:
    return subprocess.Popen([BIN / "qnav-robot", "--can", f"virtual:map-{port}", "--storage", storage, "--policy",
                             policy, "--mavlink", f"udpout:127.0.0.1:{port}", "--stats-json", stats, "-q"],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _qnav(*argv) -> subprocess.CompletedProcess:
    return subprocess.run([BIN / "qnav", *map(str, argv)], capture_output=True, text=True, timeout=120)


def test_a_sector_robot_takes_the_uploaded_map_and_boots_it_again(tmp_path):
    storage, port = tmp_path / "robot", free_udp_port()
    url = f"udpin:127.0.0.1:{port}"
    robot = _robot(storage, "policies:sector", port, tmp_path / "stats1.json")
    try:
        up = _qnav("map", "upload", "rooms-16x16-s1", "--mavlink", url, "--no-tlog")
        assert up.returncode == 0, up.stderr
        assert "map rooms-16x16-s1 (16x16 cells) active on the robot" in up.stdout
        active = storage / "maps" / "active.map"
        text = active.read_text()
        bad = tmp_path / "bad.map"
        bad.write_text("type octile\nheight 3\nwidth 3\nmap\n...\n.x\n")  # a short row
        refused = _qnav("map", "upload", bad, "--mavlink", url, "--no-tlog")
        assert refused.returncode != 0 and "map" in refused.stderr
        assert active.read_text() == text  # the old map stays
    finally:
        stop_process(robot)
    log = (storage / "logs" / "robot.log").read_text()
    assert "map 16x16 cells of 500 mm active" in log
    # a restart boots the map it was given (its storage), not the policy's paper10
    robot = _robot(storage, "policies:sector", port, tmp_path / "stats2.json")
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and (storage / "logs" / "robot.log").read_text().count(
            "map 16x16 cells of 500 mm active") < 2:
        time.sleep(0.1)
    stop_process(robot)
    log2 = (storage / "logs" / "robot.log").read_text()
    assert log2.count("map 16x16 cells of 500 mm active") == 2


def test_a_cell_policy_refuses_a_map_other_than_its_own_naming_both(tmp_path):
    storage, port = tmp_path / "robot", free_udp_port()
    robot = _robot(storage, "policies:paper10_cell", port, tmp_path / "stats.json")
    try:
        refused = _qnav("map", "upload", "rooms-16x16-s1", "--mavlink", f"udpin:127.0.0.1:{port}", "--no-tlog")
    finally:
        stop_process(robot)
    assert refused.returncode == 3, refused.stderr
    assert "map refused: policy map paper10 (10x10" in refused.stderr and "is not the robot's map (16x16" in refused.stderr
    assert not (storage / "maps" / "active.map").exists()


def test_missions_by_target_name_use_the_map_the_robot_was_given_not_its_policys(tmp_path):
    """Issue 45: after `qnav map upload`, `qnav mission upload --targets` without --map places the
    targets of the uploaded map (its targets sidecar on the robot), not those of the map the
    active policy carries (paper10, whose A and B lie elsewhere)."""
    import numpy as np

    from firmware_py import robot_spec
    from firmware_py.shipped_policies import resolve_policy_spec
    from ground_station.maps import GridMap, write_map

    occ = np.zeros((8, 12), dtype=bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    occ[4, 3:9] = True
    shop = GridMap("shop", occ, targets={"A": (1, 1), "B": (10, 6)})
    write_map(tmp_path / "shop.map", shop)
    storage, port = tmp_path / "robot", free_udp_port()
    (storage / "policies").mkdir(parents=True)
    (storage / "policies" / "active.qtab").write_bytes(Path(resolve_policy_spec("policies:sector")).read_bytes())
    url = f"udpin:127.0.0.1:{port}"
    robot = subprocess.Popen([BIN / "qnav-robot", "--can", f"virtual:map-{port}", "--storage", storage,
                              "--mavlink", f"udpout:127.0.0.1:{port}", "-q"],
                             stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        up = _qnav("map", "upload", tmp_path / "shop.map", "--mavlink", url, "--no-tlog")
        assert up.returncode == 0, up.stderr
        assert "targets A, B kept beside it" in up.stdout
        mission = _qnav("mission", "upload", "--targets", "A,B", "--no-plan", "--mavlink", url, "--no-tlog")
        assert mission.returncode == 0, mission.stderr
        down = _qnav("mission", "download", "--mavlink", url, "--no-tlog")
        assert down.returncode == 0, down.stderr
    finally:
        stop_process(robot)
    lines = [ln for ln in down.stdout.splitlines() if " m east " in ln]  # global items (lat/lon) with their metres
    got = [(float(ln.split("x=")[1].split()[0]), float(ln.split("y=")[1].split()[0])) for ln in lines]
    want = [tuple(v / 1000 for v in robot_spec.cell_center_mm(c, r, 8)) for c, r in ((1, 1), (10, 6))]
    assert len(got) == 2 and all(abs(g[0] - w[0]) < 0.01 and abs(g[1] - w[1]) < 0.01 for g, w in zip(got, want, strict=True)), \
        (down.stdout, want)
