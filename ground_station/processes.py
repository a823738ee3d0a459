"""Our programs as child processes, for the rigs, benches, fault scenarios and the demo.

`program_argv` runs a program's `main()` with this interpreter and SIGINT
restored (a parent started in the background passes SIGINT ignored on to its
children, which would then never end cleanly); `ChildProcess` is one child,
its output in a log file, stopped for sure (SIGINT so it writes its outputs,
then SIGTERM, SIGKILL); `ProcessGroup` several, each in its own session,
stopped in order.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from ground_station.subprocs import (
    die_with_parent_code,
    exit_code,
    signal_process,
    stop_process,
    wait_exit,
)

ROBOT_MAIN = "firmware_py.cli:program"  # the console scripts' entry points (pyproject.toml [project.scripts])
SIM_MAIN = "sim_bridge.cli:main"


def program_argv(entry: str, name: str, *, die_with_parent: bool = False) -> list[str]:
    """argv prefix running entry point `entry` ("module:function") as program `name` (its argv[0], so
    its usage and error lines read as usual), with SIGINT restored; `die_with_parent`: SIGTERM when
    this process dies (subprocs.die_with_parent_code)."""
    module, func = entry.split(":")
    return [sys.executable, "-c",
            (die_with_parent_code() if die_with_parent else "")
            + "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
            f"sys.argv[0] = {name!r}; from {module} import {func}; sys.exit({func}())"]


def qnav_robot(*args: str | Path, die_with_parent: bool = False) -> list[str]:
    return [*program_argv(ROBOT_MAIN, "qnav-robot", die_with_parent=die_with_parent), *map(str, args)]


def qnav_sim(*args: str | Path, die_with_parent: bool = False) -> list[str]:
    return [*program_argv(SIM_MAIN, "qnav-sim", die_with_parent=die_with_parent), *map(str, args)]


class ChildProcess:
    """One child process (module docstring): a context manager, or `start()` and `stop()`."""

    def __init__(self, argv: list[str], log: Path | None, *, own_group: bool = False,
                 append_log: bool = False) -> None:
        self.argv = [str(a) for a in argv]
        self.log = Path(log) if log is not None else None
        self.own_group = own_group
        self.append_log = append_log
        self.env: dict[str, str] = {}  # added to the child's environment
        self.proc: subprocess.Popen | None = None

    def start(self) -> ChildProcess:
        env = dict(os.environ, MAVLINK20="1", PYTHONUNBUFFERED="1", **self.env)
        if self.log is None:
            self.proc = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                         stderr=subprocess.DEVNULL, env=env, start_new_session=self.own_group)
            return self
        self.log.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log, "ab" if self.append_log else "wb") as out:  # the child keeps its own copy
            self.proc = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL, stdout=out,
                                         stderr=subprocess.STDOUT, env=env, start_new_session=self.own_group)
        return self

    @property
    def alive(self) -> bool:
        return self.proc is not None and exit_code(self.proc) is None

    @property
    def returncode(self) -> int | None:  # exit_code, not poll(): see subprocs.exit_code
        return None if self.proc is None else exit_code(self.proc)

    def wait(self, timeout_s: float | None = None) -> int:
        """Its exit code; raises subprocess.TimeoutExpired if it still runs after timeout_s."""
        assert self.proc is not None, "not started"
        return self.proc.wait(timeout=timeout_s)

    def stop(self, grace_s: float = 20.0) -> int | None:
        """SIGINT (a clean exit: outputs and stats written), then SIGTERM and SIGKILL if it
        hangs; the exit code (None if never started)."""
        proc = self.proc
        if proc is None:
            return None
        if exit_code(proc) is None:
            signal_process(proc, signal.SIGINT, group=self.own_group)
            if wait_exit(proc, grace_s) is None:
                stop_process(proc, 5.0, signal.SIGTERM, group=self.own_group)
        return exit_code(proc)

    def log_text(self) -> str:
        try:
            return self.log.read_text(errors="replace") if self.log is not None else ""
        except OSError:
            return ""

    def log_tail(self, n: int = 5) -> str:
        return " | ".join(self.log_text().splitlines()[-n:])

    def __enter__(self) -> ChildProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class ProcessGroup:
    """Named children, each in its own session/process group, stopped in the order started."""

    def __init__(self) -> None:
        self.children: list[tuple[str, ChildProcess]] = []

    def start(self, name: str, argv: list[str], log: Path) -> ChildProcess:
        child = ChildProcess(argv, log, own_group=True).start()
        self.children.append((name, child))
        return child

    def dead(self) -> list[tuple[str, int]]:
        """(name, exit code) of the children that have ended."""
        return [(name, c.returncode) for name, c in self.children if c.returncode is not None]

    def stop_all(self, grace_s: float = 15.0) -> dict[str, int | None]:
        """Stop each (SIGINT, grace_s, then SIGTERM, SIGKILL); their exit codes by name."""
        return {name: child.stop(grace_s) for name, child in self.children}
