"""Run a docs page's ```sh blocks in order as a user would: bash in a scratch folder with the venv's
programs on the PATH; the `# setup` block is this test's own environment and is skipped; the one
`# terminal 2` block (a `qnav sitl`) runs in the background until `stop()`, which sends it Ctrl-C
(SIGINT to its process group); every other block runs with `bash -e` and must exit 0. Used by
tests/hil/test_walkthrough.py (docs/walkthrough.md) and tests/hil/test_your_robot_e2e.py
(docs/your-robot.md); `interrupt` is the Ctrl-C of any background `qnav sitl`."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

BLOCK = re.compile(r"```sh\n(.*?)```", re.S)


def blocks(page: Path) -> list[str]:
    return BLOCK.findall(page.read_text())


class PageRun:
    """One run of a page's blocks in `cwd`; `edit(block) -> block` applies the test's visible
    substitutions (a free port, fewer training steps, another profile)."""

    def __init__(self, page: Path, cwd: Path, edit: Callable[[str], str]) -> None:
        self.page, self.cwd, self.edit = page, cwd, edit
        self.env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
        self.env.pop("QNAV_MAVLINK", None)
        self.sitl: subprocess.Popen | None = None
        self.sitl_out = cwd / "sitl.out"

    def run(self, after: Callable[[str, subprocess.CompletedProcess], None] | None = None,
            up_timeout_s: float = 90.0, block_timeout_s: float = 300.0) -> None:
        """Every block in order; `after(script, done)` checks each foreground block's output."""
        for block in blocks(self.page):
            script = self.edit(block)
            if script.startswith("# setup"):
                continue
            if script.startswith("# terminal 2"):
                self.sitl = subprocess.Popen(["bash", "-c", script], cwd=self.cwd, env=self.env,
                                             start_new_session=True, stdout=self.sitl_out.open("w"),
                                             stderr=subprocess.STDOUT)
                deadline = time.monotonic() + up_timeout_s
                while "Ctrl-C stops every process" not in self.sitl_out.read_text():
                    assert self.sitl.poll() is None and time.monotonic() < deadline, self.sitl_out.read_text()[-3000:]
                    time.sleep(0.2)
                continue
            done = subprocess.run(["bash", "-e", "-c", script], cwd=self.cwd, env=self.env, capture_output=True,
                                  text=True, timeout=block_timeout_s)
            assert done.returncode == 0, (script, done.stdout[-3000:], done.stderr[-3000:])
            if after is not None:
                after(script, done)

    def stop(self) -> int | None:
        """Ctrl-C the background block (as its terminal would); its exit status (None: none ran)."""
        return None if self.sitl is None else interrupt(self.sitl, self.sitl_out)


def interrupt(sitl: subprocess.Popen, out: Path, timeout_s: float = 240.0) -> int:
    """Ctrl-C a `qnav sitl` started in its own session (SIGINT to its process group) and its exit
    status; it writes run.mcap from the whole run before it exits. Still running after `timeout_s`:
    its threads' stacks (SIGUSR1), then SIGKILL and an AssertionError with its output's tail."""
    if sitl.poll() is None:
        os.killpg(sitl.pid, signal.SIGINT)
        try:
            sitl.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(sitl.pid, signal.SIGUSR1)  # qnav sitl prints its threads' stacks
            time.sleep(2)
            os.killpg(sitl.pid, signal.SIGKILL)
            sitl.wait(timeout=10)
            raise AssertionError(f"qnav sitl still running {timeout_s:.0f} s after Ctrl-C: "
                                 + out.read_text()[-3000:]) from None
    return sitl.returncode
