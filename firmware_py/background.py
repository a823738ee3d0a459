"""Work a policy kind does off the control tick (the local planner's search).

The tick must not wait on a search whose size a policy file or the obstacles choose. A kind *posts*
a job here and reads the job's last result on a later tick; a newer job from the same owner replaces
one not started yet (only the latest question matters). Two shells run the jobs, chosen by how the
robot keeps time:

* threaded (wall clock, paced HIL): one daemon worker thread, started on the first post; the tick
  never blocks on it.
* stepped (lockstep HIL, the twin's bench): `run_pending()` is called by whoever owns the schedule
  between two ticks (the node after it answered a SimTick, the twin after each period), so a job
  posted on tick k has its result on tick k+1 whatever the machine's load: runs stay reproducible.

A job that raises is logged once and counted; it never reaches the tick.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

log = logging.getLogger("qnav.background")


class Background:
    """Latest-wins jobs per owner, run by a worker thread or by `run_pending`."""

    def __init__(self, threaded: bool = True) -> None:
        self.threaded = threaded
        self._jobs: dict[int, Callable[[], None]] = {}
        self._cv = threading.Condition()
        self._thread: threading.Thread | None = None
        self._closed = False
        self.runs = 0  # jobs run
        self.errors = 0  # jobs that raised
        self.cpu_ns = 0  # thread CPU time spent in jobs (benchmarks: the cost moved off the tick)
        self.max_cpu_ns = 0  # the longest job

    def post(self, owner: object, job: Callable[[], None]) -> None:
        """Queue `job` for `owner`, replacing the owner's job not started yet."""
        with self._cv:
            if self._closed:
                return
            self._jobs[id(owner)] = job
            if self.threaded:
                if self._thread is None:
                    self._thread = threading.Thread(target=self._worker, name="qnav-background", daemon=True)
                    self._thread.start()
                self._cv.notify()

    def run_pending(self) -> int:
        """Stepped shell: run every queued job in the calling thread; how many ran."""
        n = 0
        while True:
            with self._cv:
                if not self._jobs:
                    return n
                _, job = self._jobs.popitem()
            self._run(job)
            n += 1

    def close(self) -> None:
        """Stop the worker (jobs not started are dropped)."""
        with self._cv:
            self._closed = True
            self._jobs.clear()
            self._cv.notify_all()
            t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout=5.0)

    def _run(self, job: Callable[[], None]) -> None:
        c0 = time.thread_time_ns()
        try:
            job()
        except Exception:  # a planner bug must never reach the tick: the tick sees no new result
            self.errors += 1
            if self.errors == 1:
                log.exception("background job failed (logged once, counted in errors)")
        spent = time.thread_time_ns() - c0
        self.cpu_ns += spent
        self.max_cpu_ns = max(self.max_cpu_ns, spent)
        self.runs += 1

    def _worker(self) -> None:
        while True:
            with self._cv:
                while not self._jobs and not self._closed:
                    self._cv.wait()
                if self._closed:
                    return
                # oldest owner first: dicts keep insertion order, and a re-posted job keeps its place
                key = next(iter(self._jobs))
                job = self._jobs.pop(key)
            self._run(job)
