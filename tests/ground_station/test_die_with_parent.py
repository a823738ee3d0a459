"""A `qnav sitl` (or demo) killed outright must not leave its children running: the sim, robot and
CAN hub it starts in their own sessions get SIGTERM when it dies (subprocs.die_with_parent_code).
Real processes: a starter process that starts the children as sitl does, then is SIGKILLed."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl(PR_SET_PDEATHSIG) is Linux's")

STARTER = textwrap.dedent("""
    import json, sys, time
    from pathlib import Path
    from ground_station.canhub import CanHub
    from ground_station.processes import ProcessGroup, qnav_sim
    out = Path(sys.argv[1])
    hub = CanHub(channel="orphans").start()
    procs = ProcessGroup()
    sim = procs.start("sim", qnav_sim("--map", "paper10", "--can", hub.spec, "--lockstep", "--duration", "600",
                                      "-q", die_with_parent=True), out / "sim.log")
    plain = procs.start("plain", [sys.executable, "-c", "import time; time.sleep(60)"], out / "plain.log")
    (out / "pids.json").write_text(json.dumps({"hub": hub._proc.pid, "sim": sim.proc.pid,
                                               "plain": plain.proc.pid}))
    time.sleep(600)
""")


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def test_children_started_to_die_with_their_starter_do_and_others_do_not(tmp_path):
    starter = subprocess.Popen([sys.executable, "-c", STARTER, str(tmp_path)], cwd=os.getcwd())
    pids: dict[str, int] = {}
    try:
        deadline = time.monotonic() + 60
        while not (tmp_path / "pids.json").exists():
            assert starter.poll() is None and time.monotonic() < deadline, "the starter did not start its children"
            time.sleep(0.1)
        pids = json.loads((tmp_path / "pids.json").read_text())
        assert all(_alive(p) for p in pids.values())
        starter.send_signal(signal.SIGKILL)
        starter.wait(10)
        deadline = time.monotonic() + 20
        while (_alive(pids["hub"]) or _alive(pids["sim"])) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(pids["hub"]) and not _alive(pids["sim"])  # gone with the starter
        assert _alive(pids["plain"])  # a child not asked to die with it lives on (its own session)
    finally:
        for pid in pids.values():
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        if starter.poll() is None:
            starter.kill()
