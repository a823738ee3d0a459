"""Result type and registry shared by the fault scenarios, and the robot process they run."""

from __future__ import annotations

import functools
import signal
import socket
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ground_station.processes import ChildProcess, qnav_robot
from ground_station.subprocs import exit_code, free_udp_port, signal_process

MAX_FAILURES_KEPT = 20


@dataclass
class ScenarioResult:
    """Outcome of `tried` trials: `survived` kept the invariant, the rest are lost.

    `failures` holds one line per lost trial (the first MAX_FAILURES_KEPT);
    `figures` carries measured numbers worth reporting (counters, rates)."""

    name: str
    tried: int = 0
    survived: int = 0
    failures: list[str] = field(default_factory=list)
    figures: dict[str, Any] = field(default_factory=dict)  # JSON-ready numbers and nested dicts

    @property
    def lost(self) -> int:
        return self.tried - self.survived

    @property
    def ok(self) -> bool:
        return self.tried > 0 and self.lost == 0

    def trial(self, ok: bool, why: str = "") -> None:
        """Count one trial; `why` says what broke when it did not hold."""
        self.tried += 1
        if ok:
            self.survived += 1
        elif len(self.failures) < MAX_FAILURES_KEPT:
            self.failures.append(why or "invariant violated")

    def check(self, problems: list[str], label: str) -> None:
        """A trial that holds when `problems` is empty."""
        self.trial(not problems, f"{label}: {'; '.join(problems)}")

    def as_dict(self) -> dict:
        return {"name": self.name, "tried": self.tried, "survived": self.survived, "lost": self.lost,
                "failures": self.failures, "figures": self.figures}


Runner = Callable[..., ScenarioResult]
Body = Callable[..., None]  # a scenario as written: fills in the result it is handed


def trials(count: int, progress: Any = None) -> Iterator[int]:
    """0 .. count - 1, one a trial, ticking `progress` (a bar with `update`, or None) after each
    trial's body: the scenarios' loops, so that none repeats the tick."""
    for i in range(count):
        yield i
        if progress is not None:
            progress.update(1)


@dataclass(frozen=True)
class Scenario:
    name: str
    run: Runner
    small: int  # count in tests/faults (make test)
    large: int  # count in qnav bench faults
    unit: str  # what one trial is
    what: str  # one-line description of the invariant


SCENARIOS: dict[str, Scenario] = {}


def register(name: str, small: int, large: int, unit: str, what: str) -> Callable[[Body], Runner]:
    """Register the scenario `name` given as its body, `body(res, count, seed, progress, **options)`,
    which fills in `res`; the runner it becomes, `run(count, seed=0, progress=None, **options)`,
    makes that result under the registered name and returns it, so no scenario repeats either."""
    def deco(body: Body) -> Runner:
        @functools.wraps(body)
        def run(count: int, seed: int = 0, progress: Any = None, **options: Any) -> ScenarioResult:
            res = ScenarioResult(name)
            body(res, count, seed, progress, **options)
            return res
        SCENARIOS[name] = Scenario(name, run, small, large, unit, what)
        return run
    return deco


class RobotProcess(ChildProcess):
    """`qnav-robot` listening for MAVLink on `udpin:127.0.0.1:PORT`, its storage in `storage`.
    Without `can` it gets a private in-process `virtual` bus: no sensors, so it stays disarmed in
    STANDBY, all that uploads, activations and parameter saves need. Its log is appended to (a
    restarted robot adds to it). `stop()`'s 20 s grace: its shutdown joins two 5 s threads.

    `start()` returns once the robot said READY (sd_notify, as under systemd: its MAVLink port is
    bound and its control loop runs) or exited. A port this class picked itself can be taken by a
    process beside it between the pick and the robot's bind; then the robot exits 2 with "Address
    already in use", and `start()` picks another port and starts it again (BIND_TRIES in all)."""

    BIND_TRIES = 3
    READY_WAIT_S = 30.0

    def __init__(self, storage: Path, *, port: int | None = None, key_file: Path | None = None,
                 can: str | None = None, extra: list[str] | None = None, log: Path | None = None) -> None:
        self.storage = Path(storage)
        self.own_port = port is None
        self.port = port or free_udp_port()
        self._args = ["--can", can or f"virtual:rig-{uuid.uuid4().hex}", "--storage", str(self.storage)]
        if key_file is not None:
            self._args += ["--signing-key", str(key_file)]
        self._args += extra or []
        super().__init__(self._argv(), log or self.storage.parent / f"robot-{self.port}.log", append_log=True)

    def _argv(self) -> list[str]:
        return qnav_robot(*self._args, "--mavlink", f"udpin:127.0.0.1:{self.port}")

    @property
    def url(self) -> str:
        """What a ground station connects to (directly, without the emulator)."""
        return f"udpout:127.0.0.1:{self.port}"

    def start(self) -> RobotProcess:
        self.storage.mkdir(parents=True, exist_ok=True)
        for attempt in range(self.BIND_TRIES):
            log_size = self.log.stat().st_size if self.log is not None and self.log.exists() else 0
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as ready:
                name = f"qnav-rig-ready-{uuid.uuid4().hex}"
                ready.bind("\0" + name)  # an abstract socket: nothing to clean up
                self.env["NOTIFY_SOCKET"] = "@" + name
                super().start()
                self._wait_ready(ready)
            if not (self.own_port and attempt + 1 < self.BIND_TRIES and self.returncode == 2
                    and "Address already in use" in self.log_text()[log_size:]):
                return self
            self.port = free_udp_port()
            self.argv = self._argv()
        return self

    def _wait_ready(self, ready: socket.socket) -> None:
        deadline = time.monotonic() + self.READY_WAIT_S
        ready.settimeout(0.1)
        while self.alive and time.monotonic() < deadline:
            try:
                if b"READY=1" in ready.recv(4096).split(b"\n"):
                    return
            except TimeoutError:
                continue

    def __enter__(self) -> RobotProcess:
        return self.start()

    def kill9(self) -> None:
        """The crash: SIGKILL, no clean-up in the child."""
        proc = self.proc
        if proc is not None and exit_code(proc) is None:
            signal_process(proc, signal.SIGKILL, group=self.own_group)
            proc.wait(timeout=10)
