"""A throwaway Ray cluster on this machine: a head node and worker nodes,
each started by `ray start` as separate processes, for tests and demos of
the Ray engine.

Each cluster gets its own ports, its own `--temp-dir` and its own token
(Ray's token authentication), and `stop()` ends exactly the processes that
carry that temp dir or GCS port on their command line, never another Ray
on the machine (`ray stop` would end them all). Ray's own services listen
on every interface; the token is what keeps other hosts out.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ground_station.lab.rigs import other_processes


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LocalRayCluster:
    """`ray start --head` plus `workers` x `ray start --address`, 1 CPU per node."""

    def __init__(self, root: Path, workers: int = 1, cpus_per_node: int = 1) -> None:
        self.root = Path(root)
        self.port = _free_tcp_port()
        # Ray puts AF_UNIX sockets under its temp dir (107-byte limit): keep that path short.
        self.temp_dir = Path(tempfile.mkdtemp(prefix="qray", dir="/tmp"))
        self.workers = workers
        self.cpus = cpus_per_node
        self.token_path = self.root / "ray_token"
        self.address = f"127.0.0.1:{self.port}"

    def env(self) -> dict[str, str]:
        """The environment a driver or node of this cluster needs."""
        env = dict(os.environ)
        # RAY_worker_niceness: Ray starts its worker processes at nice 15, below its own services; on a
        # machine shared with other work (a test suite beside busy processes) they then got a sliver of
        # the CPU and a 35 s Tune test took 275 s. On this cluster the workers are the work: nice 0.
        env.update({"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN_PATH": str(self.token_path),
                    "RAY_USAGE_STATS_ENABLED": "0", "RAY_worker_niceness": "0"})
        repo = str(Path(__file__).resolve().parents[3])
        env["PYTHONPATH"] = repo + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        return env

    def _ray(self, *args: str) -> None:
        ray_cli = shutil.which("ray", path=os.path.dirname(sys.executable)) or "ray"
        res = subprocess.run([ray_cli, "start", *args, "--num-cpus", str(self.cpus), "--node-ip-address",
                              "127.0.0.1", "--disable-usage-stats"], env=self.env(), capture_output=True,
                             text=True, timeout=120, check=False)
        if res.returncode != 0:
            raise RuntimeError(f"ray start {' '.join(args[:2])} failed: {(res.stderr or res.stdout)[-800:]}")

    def start(self) -> LocalRayCluster:
        self.root.mkdir(parents=True, exist_ok=True)
        self.token_path.write_text(secrets.token_hex(32))
        os.chmod(self.token_path, 0o600)
        # Ray waits a fixed 30 s for a node's raylet to register (ray/_private/node.py); beside other work
        # on 2 cores the head missed it ("timed out during startup"): its processes stopped, it starts again
        for attempt in range(3):
            try:
                self._ray("--head", "--port", str(self.port), "--include-dashboard=false", "--temp-dir",
                          str(self.temp_dir))
                break
            except RuntimeError as exc:
                if "timed out during startup" not in str(exc) or attempt == 2:
                    raise
                self.stop()
        for _ in range(self.workers):
            self._ray("--address", self.address)
        self.wait_nodes(1 + self.workers)
        return self

    def wait_nodes(self, n: int, timeout_s: float = 60.0) -> None:
        code = ("import ray, sys; ray.init(address=sys.argv[1], log_to_driver=False); "
                "print(sum(1 for x in ray.nodes() if x['Alive']))")
        deadline = time.monotonic() + timeout_s
        alive = 0
        while time.monotonic() < deadline:
            res = subprocess.run([sys.executable, "-c", code, self.address], env=self.env(), capture_output=True,
                                 text=True, timeout=60, check=False)
            alive = int(res.stdout.strip() or 0) if res.returncode == 0 else 0
            if alive >= n:
                return
            time.sleep(1.0)
        raise RuntimeError(f"Ray cluster at {self.address}: {alive} of {n} nodes alive after {timeout_s:.0f} s")

    def pids(self) -> list[int]:
        """Processes of this cluster: their command line names its temp dir or GCS port."""
        marks = (str(self.temp_dir), f":{self.port}")
        return [pid for pid, cmd in other_processes() if any(m in cmd for m in marks)]

    def stop(self, timeout_s: float = 10.0) -> None:
        for sig in (signal.SIGTERM, signal.SIGKILL):
            pids = self.pids()
            for pid in pids:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, sig)
            deadline = time.monotonic() + timeout_s
            while pids and time.monotonic() < deadline:
                pids = [p for p in pids if os.path.exists(f"/proc/{p}") and not _zombie(p)]
                time.sleep(0.2)
            if not pids:
                break
        shutil.rmtree(self.temp_dir, ignore_errors=True)

    def __enter__(self) -> LocalRayCluster:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"
    except (OSError, IndexError):
        return True
