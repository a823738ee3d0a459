"""The robot's own log: `logs/robot.log` under its storage root, size-capped and rotated.

What goes in: every record of the `qnav` loggers at INFO and above (state transitions with their
cause, faults, refusals, policy activations, MAVLink and CAN warnings) and one `stats` line per
second (state, ticks, overruns, CAN errors, the worst tick latency of that second). The robot's FTP
server serves the storage root, so `qnav log list|pull` fetch it over the link (docs/deploy.md).

The control tick never waits on the file: records go through a queue (logging's QueueHandler) to a
listener thread that does the writing, and rotation (RotatingFileHandler: MAX_BYTES per file,
BACKUPS old files, robot.log.1 ... robot.log.N) happens there too. Stdlib only.
"""

from __future__ import annotations

import contextlib
import logging
import logging.handlers
import queue
import threading
from collections.abc import Callable
from pathlib import Path

LOG_DIR = "logs"
LOG_NAME = "robot.log"
MAX_BYTES = 256 * 1024
BACKUPS = 4  # 1.25 MiB at most: well inside the storage quota (storage.DEFAULT_QUOTA_BYTES)


class OnboardLog:
    """Attach with `start()`, detach with `stop()` (flushes what is queued)."""

    def __init__(self, storage_root: str | Path, stats: Callable[[], str] | None = None,
                 max_bytes: int = MAX_BYTES, backups: int = BACKUPS, period_s: float = 1.0) -> None:
        self.dir = Path(storage_root) / LOG_DIR
        self.path = self.dir / LOG_NAME
        self.stats = stats
        self.period_s = period_s
        self._queue: queue.Queue[logging.LogRecord] = queue.Queue(maxsize=10_000)
        self._file = logging.handlers.RotatingFileHandler(self.path, maxBytes=max_bytes, backupCount=backups,
                                                          encoding="utf-8", delay=True)
        self._file.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s %(message)s"))
        self._handler = _DroppingQueueHandler(self._queue)
        self._handler.setLevel(logging.INFO)
        self._listener = logging.handlers.QueueListener(self._queue, self._file)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._logger = logging.getLogger("qnav")
        self._old_level = self._logger.level

    def start(self) -> OnboardLog:
        self.dir.mkdir(parents=True, exist_ok=True)
        self._listener.start()
        self._logger.addHandler(self._handler)
        if self._logger.getEffectiveLevel() > logging.INFO:  # `--quiet` on the console, not in the log
            self._logger.setLevel(logging.INFO)
        logging.getLogger("qnav.robot").info("onboard log started (%s)", self.path)
        if self.stats is not None:
            self.start_stats(self.stats)
        return self

    def start_stats(self, stats: Callable[[], str]) -> None:
        """The per-second stats line from now on (the robot's node exists only after boot)."""
        self.stats = stats
        self._thread = threading.Thread(target=self._stats_loop, name="qnav-log-stats", daemon=True)
        self._thread.start()

    def _stats_loop(self) -> None:
        log = logging.getLogger("qnav.stats")
        while not self._stop.wait(self.period_s):
            try:
                log.info("%s", self.stats() if self.stats else "")
            except Exception:  # a stats bug must not end the log
                log.exception("stats line failed")

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        self._logger.removeHandler(self._handler)
        self._logger.setLevel(self._old_level)
        self._listener.stop()  # writes what is queued
        self._file.close()


class _DroppingQueueHandler(logging.handlers.QueueHandler):
    """Never blocks the caller: a full queue (the disk stalled) drops the record."""

    def enqueue(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(queue.Full):
            self.queue.put_nowait(record)
