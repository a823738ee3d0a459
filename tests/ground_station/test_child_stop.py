"""Stopping children when Popen's waitpid lock is held: what a KeyboardInterrupt landing in
Popen.poll() leaves (subprocs.exit_code), which made a Ctrl-C'd `qnav demo` / `qnav sitl` wait for
ever on a child that had already exited. Real processes; the lock is taken as the interrupt leaves it."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

from ground_station.processes import ChildProcess
from ground_station.subprocs import exit_code, stop_process, wait_exit


def _held(proc: subprocess.Popen) -> None:
    assert proc._waitpid_lock.acquire(False)  # as a KeyboardInterrupt just after poll()'s take leaves it


def test_exit_code_sees_the_end_with_the_lock_held_and_leaves_the_child_to_reap():
    proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.exit(3)"])
    _held(proc)
    deadline = time.monotonic() + 30
    while exit_code(proc) is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert exit_code(proc) == 3
    assert proc.poll() is None  # what poll() says with the lock held: "running"
    proc._waitpid_lock.release()
    assert proc.wait(timeout=5) == 3  # not reaped by exit_code: Popen still gets the code


def test_a_signal_death_is_a_negative_code():
    proc = subprocess.Popen(["sleep", "30"])
    assert exit_code(proc) is None
    proc.send_signal(signal.SIGTERM)
    assert wait_exit(proc, 10.0) == -signal.SIGTERM


def test_child_stop_returns_with_the_lock_held(tmp_path):
    child = ChildProcess(["sleep", "30"], tmp_path / "sleep.log", own_group=True).start()
    assert child.proc is not None
    _held(child.proc)
    assert child.alive
    t0 = time.monotonic()
    assert child.stop(grace_s=20.0) == -signal.SIGINT  # was: 20 s + 5 s, SIGKILL, then wait() for ever
    assert time.monotonic() - t0 < 5.0
    assert not child.alive and child.returncode == -signal.SIGINT


def test_stop_process_escalates_to_sigkill_and_says_so():
    proc = subprocess.Popen([sys.executable, "-c",
                             "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                             "print('ready', flush=True); time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    _held(proc)
    assert stop_process(proc, timeout_s=0.5) == -signal.SIGKILL
