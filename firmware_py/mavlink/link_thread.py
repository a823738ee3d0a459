"""The MAVLink side's threads in `qnav-robot`: the link thread and the storage worker.

The control loop never touches the link: after each tick it only runs `LinkThread.on_tick` (the
GCS failsafe check and an event that opens the link thread's slot); `LinkThread` then runs one
`MavShell.poll` budgeted to `budget_fraction` of the control period, and `StorageWorker` runs the
parameter saves off both threads. The schedule (as ArduPilot's scheduler), the switch interval and
the poll's GIL yields: docs/mavlink.md, "Node structure".
"""

from __future__ import annotations

import logging
import queue
import sys
import threading
import time
from collections.abc import Callable

from firmware_py.clock import Clock
from firmware_py.mavlink.node import MavShell

log = logging.getLogger("qnav.mavlink")

DEFAULT_SWITCH_INTERVAL_S = 0.0005
DEFAULT_BUDGET_FRACTION = 0.4
DEFAULT_YIELD_EVERY_S = 0.001  # after 1 ms of link work, 0.2 ms with the interpreter lock free


class StorageWorker:
    """One thread running storage jobs in order; a job whose key is already
    queued is absorbed by it (the queued job writes the newest state)."""

    def __init__(self, maxsize: int = 32) -> None:
        self._q: queue.Queue[tuple[str, Callable[[], None]] | None] = queue.Queue(maxsize)
        self._lock = threading.Lock()
        self._queued: set[str] = set()
        self._idle = threading.Condition(self._lock)
        self._busy = 0  # submitted and not finished
        self.done = 0
        self.coalesced = 0
        self.dropped = 0  # queue full: the job was not run (the state stays in memory)
        self.errors = 0
        self._thread = threading.Thread(target=self._run, name="qnav-storage", daemon=True)
        self._thread.start()

    def submit(self, key: str, job: Callable[[], None]) -> bool:
        """Queue `job` unless one with `key` is already queued. Never blocks."""
        with self._lock:
            if key in self._queued:
                self.coalesced += 1
                return True
            try:
                self._q.put_nowait((key, job))
            except queue.Full:
                self.dropped += 1
                return False
            self._queued.add(key)
            self._busy += 1
            return True

    def flush(self, timeout_s: float = 5.0) -> bool:
        """Wait until every submitted job has run; False on timeout."""
        with self._idle:
            return self._idle.wait_for(lambda: self._busy == 0, timeout_s)

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            key, job = item
            with self._lock:  # before running: a change made during the job queues another run
                self._queued.discard(key)
            try:
                job()
            except Exception as exc:  # a full disk must not kill the worker
                self.errors += 1
                if self.errors == 1:
                    log.error("storage job %s failed: %s (further failures only counted)", key, exc)
            with self._idle:
                self.done += 1
                self._busy -= 1
                self._idle.notify_all()

    def close(self, timeout_s: float = 10.0) -> None:
        """Run what is queued, then stop."""
        self._q.put(None)
        self._thread.join(timeout_s)


class LinkThread:
    """Runs a `MavShell` in its own thread, one budgeted poll per control tick."""

    def __init__(self, shell: MavShell, clock: Clock, period_us: Callable[[], int], *,
                 budget_fraction: float = DEFAULT_BUDGET_FRACTION,
                 switch_interval_s: float | None = DEFAULT_SWITCH_INTERVAL_S,
                 yield_every_s: float = DEFAULT_YIELD_EVERY_S) -> None:
        self.shell = shell
        self.clock = clock
        self.period_us = period_us
        self.budget_fraction = budget_fraction
        self.switch_interval_s = switch_interval_s
        self.yield_every_s = yield_every_s
        self.polls = 0
        self.frames = 0
        self.unslotted_polls = 0  # polls without a control tick (none for two periods)
        self.poll_max_s = 0.0
        self.failsafe_errors = 0
        self._go = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        shell.node.failsafe_on_control = True

    def start(self) -> LinkThread:
        if self.switch_interval_s is not None:
            sys.setswitchinterval(self.switch_interval_s)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="qnav-link", daemon=True)
        self._thread.start()
        return self

    def on_tick(self, _out: object = None) -> None:
        """After-tick hook (the ticking thread): failsafe check, open the slot. Never waits on the link."""
        try:
            self.shell.node.check_failsafe(self.clock.now_us())
        except Exception as exc:  # never out into the control loop
            self.failsafe_errors += 1
            if self.failsafe_errors == 1:
                log.error("GCS failsafe check raised %s: %s", type(exc).__name__, exc)
        self._go.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            period_s = self.period_us() / 1e6
            if not self._go.wait(2 * period_s):
                self.unslotted_polls += 1
            self._go.clear()
            if self._stop.is_set():
                break
            t0 = time.perf_counter()
            try:
                self.frames += self.shell.poll(self.clock.now_us(), budget_s=period_s * self.budget_fraction,
                                               yield_every_s=self.yield_every_s)
            except Exception as exc:  # poll catches per frame; this is the socket layer itself
                self.shell.handler_errors["poll"] = self.shell.handler_errors.get("poll", 0) + 1
                if self.shell.handler_errors["poll"] == 1:
                    log.error("MAVLink poll raised %s: %s", type(exc).__name__, exc)
                time.sleep(period_s)
            self.polls += 1
            self.poll_max_s = max(self.poll_max_s, time.perf_counter() - t0)

    def stop(self) -> None:
        self._stop.set()
        self._go.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None

    def stats(self) -> dict[str, object]:
        return {"link_polls": self.polls, "link_frames": self.frames, "link_unslotted_polls": self.unslotted_polls,
                "link_poll_max_ms": round(self.poll_max_s * 1000, 3),
                "link_budget_exhausted": self.shell.budget_exhausted,
                "link_partial_dropped": self.shell.partial_dropped,
                "link_telemetry_thinned": 0 if self.shell.tx_budget is None else self.shell.tx_budget.dropped,
                "link_handler_errors": self.shell.all_handler_errors(),
                "switch_interval_us": round(sys.getswitchinterval() * 1e6)}
