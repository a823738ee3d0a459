"""`kill -USR1` on a running qnav-robot prints every thread's stack to its stderr and the robot runs on
(SIGUSR1's default action would end it): how a robot, or a test's child, that does not stop says where it is."""

from __future__ import annotations

import signal
import subprocess
import time

from ground_station.processes import qnav_robot


def test_sigusr1_dumps_the_robots_threads_and_it_runs_on():
    proc = subprocess.Popen(qnav_robot("--can", "virtual:stackdump", "--duration", "4"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        seen = ""
        deadline = time.monotonic() + 30
        while "clock" not in seen and time.monotonic() < deadline:  # "policy none, start ... wall clock"
            line = proc.stderr.readline()
            if not line:
                break
            seen += line
        assert "wall clock" in seen, seen
        proc.send_signal(signal.SIGUSR1)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err[-2000:]  # not ended by the signal
    assert "Current thread" in err and "firmware_py/cli.py" in err, err[-2000:]
    assert err.count("Thread 0x") >= 2, err[-2000:]  # the tick's thread beside the main one
