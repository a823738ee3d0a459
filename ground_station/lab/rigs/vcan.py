"""A real kernel SocketCAN `vcan0` for hardware-in-the-loop runs, wherever one can be had.

`find_vcan()` tries the providers in order and takes the first that works:

- **host**: this kernel already has `vcan0` up, or has the `vcan` module and
  we may create the interface (root: `modprobe vcan`, `ip link add dev vcan0
  type vcan`, `ip link set up vcan0`), as on an ordinary Linux PC. The work
  runs here, directly.
- **uml**: the kernel has no vcan (containers, these CI machines: `AF_CAN`
  refused), but Debian's user-mode Linux is installed (`linux.uml`, its CAN
  modules under /usr/lib/uml/modules, `insmod`, `ip`).
- **uml-cache**: a newer user-mode Linux unpacked by
  `tools/install_test_deps.sh` into the project's `.cache/uml/` (Debian
  testing's `user-mode-linux` with that suite's C library beside it), for
  hosts where the installed one panics at boot (bookworm's 6.1 and trixie's
  6.12 on CPUs with AVX-512/AMX: "ptrace set fp regs failed").
- **none**: `VcanUnavailable(reason)`, the reason naming each provider tried
  and why it failed; tests skip with it printed.

A user-mode Linux provider counts only after it has booted once in this
process (the health check: vcan0 up and an `AF_CAN` bind from Python, at most
`HEALTH_TIMEOUT_S`); the verdict is cached. `Vcan.run()` boots a Linux kernel
as an ordinary process with the host's root filesystem mounted read-write
through hostfs, so the checkout, its venv and Python are the same files. A
PID-1 script (written into the work directory) mounts proc and sysfs, loads
can, can-raw, can-dev, vcan in that order (vcan needs can-dev's symbols),
brings up `lo` (MAVLink over UDP stays on the UML's own loopback) and `vcan0`,
runs the work script with the environment given, writes its output and its
exit status into the work directory, syncs and powers off. UML's own exit
status says nothing about the work, so the status file is the only verdict:
no file, no pass. A timeout kills the UML process group (UML runs as several
host processes) and the run reports `timed_out`.

Environment: `QNAV_VCAN=host|uml|uml-cache|none` forces one provider (none:
skip); `QNAV_VCAN_HIDE=NAME[,NAME]` hides providers from the search (to see
what the tests do on a machine without them); `QNAV_UML_CACHE=DIR` moves the
cache. `python -m ground_station.lab.rigs.vcan` prints every provider's verdict.

Work is a shell script (run by /bin/sh in `cwd`); everything it produces
should go under the work directory, which both sides see. Inside UML system
calls are slow (tick p99 ~14 ms measured against ~1 ms on the host), so
runs there prove the kernel SocketCAN path, not timing.

    vcan = find_vcan()            # raises VcanUnavailable with the reason
    run = vcan.run("candump -L vcan0 -n 1 > got.log & cansend vcan0 123#01; wait",
                   workdir, timeout_s=60)
    assert run.exit_status == 0, run.describe()
"""

from __future__ import annotations

import contextlib
import os
import shlex
import shutil
import signal
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

CHANNEL = "vcan0"
UML_KERNEL = "linux.uml"
UML_MODULES = Path("/usr/lib/uml/modules")
# the newer UML that tools/install_test_deps.sh unpacks where the installed one does not boot
UML_CACHE = Path(__file__).resolve().parents[3] / ".cache" / "uml"
# load order matters: vcan needs can-dev's symbols, can-raw needs can's
UML_CAN_MODULES = ("net/can/can.ko", "net/can/can-raw.ko", "drivers/net/can/dev/can-dev.ko",
                   "drivers/net/can/vcan.ko")
SBIN = ("/usr/local/sbin", "/usr/sbin", "/sbin")
UML_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
# what the work inherits when the caller passes no env (PID 1 starts with an empty one)
PASSED_ENV = ("PATH", "PYTHONPATH", "HOME", "LANG", "LC_ALL", "VIRTUAL_ENV", "MAVLINK20", "TMPDIR")
PROVIDERS = ("host", "uml", "uml-cache")
HEALTH_TIMEOUT_S = 45.0  # one boot is 1-3 s here; a loaded machine may take far longer
# a bind on vcan0 from Python is what the HIL programs need (python-can's socketcan)
HEALTH_SCRIPT = ("ip -br link show {ch} && python3 -c \"import socket; "
                 "s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW); "
                 "s.bind(('{ch}',)); print('AF_CAN bind ok')\"")


class VcanUnavailable(Exception):
    """No way to a kernel vcan on this machine; the message says why."""


@dataclass
class VcanRun:
    """What came back from one `Vcan.run()`."""

    where: str  # "host" or "uml"
    exit_status: int | None  # the work's; None when no status came back (timeout, failed boot)
    output: str  # the work's stdout + stderr
    wall_s: float  # including the boot
    timed_out: bool = False
    console: str = ""  # UML: kernel console and setup messages

    def describe(self) -> str:
        """One paragraph for an assertion message."""
        why = "timed out" if self.timed_out else f"exit status {self.exit_status}"
        tail = "\n".join(self.output.splitlines()[-15:])
        text = f"vcan run ({self.where}) {why} after {self.wall_s:.1f} s\n--- output (tail) ---\n{tail}"
        if self.console and self.exit_status is None:
            text += "\n--- console (tail) ---\n" + "\n".join(self.console.splitlines()[-15:])
        return text


def _tool(name: str) -> str | None:
    """`name` on PATH or in the sbin directories a non-root PATH often lacks."""
    found = shutil.which(name)
    if found:
        return found
    for d in SBIN:
        p = Path(d) / name
        if p.is_file() and os.access(p, os.X_OK):
            return str(p)
    return None


def _host_af_can() -> bool:
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
        return True
    except (OSError, AttributeError):
        return False


def _host_vcan(channel: str, create: bool) -> str | None:
    """None if `channel` is up on this kernel (made if allowed); else why not."""
    if not _host_af_can():
        return "this kernel refuses AF_CAN sockets (no SocketCAN)"
    if Path(f"/sys/class/net/{channel}").exists():
        if not create:
            return None
        ip = _tool("ip")
        if ip:
            subprocess.run([ip, "link", "set", "up", channel], capture_output=True, check=False)
        return None
    if not create:
        return f"{channel} does not exist (and creating it was not allowed)"
    if os.geteuid() != 0:
        return f"{channel} does not exist and creating it needs root"
    modprobe, ip = _tool("modprobe"), _tool("ip")
    if not (modprobe and ip):
        return "modprobe or ip missing"
    for cmd in ([modprobe, "vcan"], [ip, "link", "add", "dev", channel, "type", "vcan"],
                [ip, "link", "set", "up", channel]):
        r = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if r.returncode != 0:
            return f"{' '.join(cmd)}: {(r.stderr or r.stdout).strip() or r.returncode}"
    return None


def _can_modules(root: Path) -> Path | None:
    """The newest UML module tree under `root` that has every CAN module we load."""
    if not root.is_dir():
        return None
    for d in sorted(root.iterdir(), reverse=True):
        if all((d / "kernel" / m).is_file() for m in UML_CAN_MODULES):
            return d
    return None


def _uml_cache() -> Path:
    return Path(os.environ.get("QNAV_UML_CACHE") or UML_CACHE)


def _uml_parts(where: str) -> tuple[str | None, Path | None, str | None]:
    """(kernel, module tree, None) for a UML provider, or (.., .., what is missing)."""
    missing = []
    if where == "uml":
        kernel = _tool(UML_KERNEL)
        modules = _can_modules(UML_MODULES)
        if kernel is None:
            missing.append(f"{UML_KERNEL} (Debian package user-mode-linux)")
        elif modules is None:
            missing.append(f"UML CAN modules under {UML_MODULES}")
    else:
        root = _uml_cache()
        k = root / "usr" / "bin" / UML_KERNEL
        kernel = str(k) if k.is_file() and os.access(k, os.X_OK) else None
        modules = _can_modules(root / "usr" / "lib" / "uml" / "modules")
        if kernel is None or modules is None:
            missing.append(f"a user-mode Linux unpacked under {root} (tools/install_test_deps.sh "
                           "unpacks one where the installed one does not boot)")
    if _tool("insmod") is None:
        missing.append("insmod (package kmod)")
    if _tool("ip") is None:
        missing.append("ip (package iproute2)")
    return kernel, modules, (f"missing {', '.join(missing)}" if missing else None)


def _boot_failure(console: str) -> str:
    """The console's most telling line for a boot that gave no status."""
    lines = [ln.strip() for ln in console.splitlines() if ln.strip()]
    for key in ("Kernel panic", "failed", "error", "Error"):
        hits = [ln for ln in lines if key in ln]
        if hits:
            return hits[0][:160]
    return lines[-1][:160] if lines else "no console output"


_health: dict[tuple[str, str], str | None] = {}


def provider_reason(where: str, channel: str = CHANNEL, *, create: bool = True) -> str | None:
    """None if provider `where` gives a working `channel` here; else why not.

    A user-mode Linux provider is booted once per process (vcan0 up and an AF_CAN
    bind, at most HEALTH_TIMEOUT_S) and its verdict cached."""
    if where == "host":
        return _host_vcan(channel, create)
    if where not in ("uml", "uml-cache"):
        return f"unknown provider {where!r} (one of {', '.join(PROVIDERS)})"
    kernel, modules, missing = _uml_parts(where)
    if missing or kernel is None or modules is None:
        return missing or "user-mode Linux vanished"
    key = (where, kernel)
    if key not in _health:
        import tempfile

        with tempfile.TemporaryDirectory(prefix=f"qnav-vcan-{where}-") as tmp:
            run = Vcan(where, channel).run(HEALTH_SCRIPT.format(ch=channel), Path(tmp), cwd=Path(tmp),
                                           timeout_s=HEALTH_TIMEOUT_S)
        if run.timed_out:
            _health[key] = f"{kernel} did not finish a boot in {HEALTH_TIMEOUT_S:.0f} s"
        elif run.exit_status is None:
            _health[key] = f"{kernel} failed to boot: {_boot_failure(run.console)}"
        elif run.exit_status != 0 or "AF_CAN bind ok" not in run.output:
            tail = (run.output.strip().splitlines() or ["no output"])[-1]
            _health[key] = f"{kernel} booted but vcan0 did not work: {tail[:160]}"
        else:
            _health[key] = None
    return _health[key]


class Vcan:
    """A way to run work with a kernel `vcan0` (see the module docstring)."""

    def __init__(self, where: str, channel: str = CHANNEL, *, mem: str = "1G") -> None:
        if where not in PROVIDERS:
            raise ValueError(f"where must be one of {', '.join(PROVIDERS)}, got {where!r}")
        self.where = where
        self.channel = channel
        self.mem = mem

    @property
    def can_spec(self) -> str:
        """The `--can` term for the HIL programs."""
        return f"socketcan:{self.channel}"

    def run(self, script: str, workdir: Path, *, cwd: Path | None = None, env: dict[str, str] | None = None,
            timeout_s: float = 90.0) -> VcanRun:
        """Run the shell `script` with `channel` up; output and status come back through `workdir`."""
        workdir = Path(workdir).resolve()
        workdir.mkdir(parents=True, exist_ok=True)
        cwd = Path(cwd or os.getcwd()).resolve()
        if env is None:
            env = {k: os.environ[k] for k in PASSED_ENV if k in os.environ}
        env.setdefault("PATH", UML_PATH)
        env["VCAN"] = self.channel
        work = workdir / "work.sh"
        exports = "".join(f"export {k}={shlex.quote(v)}\n" for k, v in sorted(env.items()))
        work.write_text(f"#!/bin/sh\n{exports}cd {shlex.quote(str(cwd))} || exit 125\n{script}\n")
        for stale in ("exit_status", "work.log", "console.log", "setup.log"):
            (workdir / stale).unlink(missing_ok=True)
        if self.where == "host":
            return self._run_host(work, workdir, timeout_s)
        return self._run_uml(work, workdir, timeout_s)

    def _run_host(self, work: Path, workdir: Path, timeout_s: float) -> VcanRun:
        t0 = time.monotonic()
        with open(workdir / "work.log", "wb") as log:
            proc = subprocess.Popen(["/bin/sh", str(work)], stdin=subprocess.DEVNULL, stdout=log,
                                    stderr=subprocess.STDOUT, start_new_session=True)
            timed_out = _wait_or_kill(proc, timeout_s)
        status = None if timed_out else proc.returncode
        return VcanRun("host", status, _read(workdir / "work.log"), time.monotonic() - t0, timed_out)

    def _run_uml(self, work: Path, workdir: Path, timeout_s: float) -> VcanRun:
        kernel, modules, missing = _uml_parts(self.where)
        if missing or modules is None or kernel is None:
            raise VcanUnavailable(missing or "user-mode Linux vanished")
        w = shlex.quote(str(workdir))
        insmods = "\n".join(f"    insmod {shlex.quote(str(modules / 'kernel' / m))} &&" for m in UML_CAN_MODULES)
        init = workdir / "init.sh"
        init.write_text(f"""#!/bin/sh
# PID 1 inside user-mode Linux, written by ground_station/lab/rigs/vcan.py
export PATH={UML_PATH}
mount -t proc proc /proc
mount -t sysfs sysfs /sys
if {{
{insmods}
    ip link set up lo &&
    ip link add dev {self.channel} type vcan &&
    ip link set up {self.channel}
}} > {w}/setup.log 2>&1; then
    /bin/sh {shlex.quote(str(work))} > {w}/work.log 2>&1 < /dev/null
    echo $? > {w}/exit_status.tmp
else
    echo "vcan setup failed" >> {w}/setup.log
    echo 125 > {w}/exit_status.tmp
fi
mv {w}/exit_status.tmp {w}/exit_status
sync
poweroff -f
""")
        init.chmod(0o755)
        cmd = [kernel, f"mem={self.mem}", "rootfstype=hostfs", "rootflags=/", "rw", f"init={init}",
               "con=null", "con0=fd:0,fd:1"]
        t0 = time.monotonic()
        with open(workdir / "console.log", "wb") as console:
            proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=console, stderr=subprocess.STDOUT,
                                    start_new_session=True)
            timed_out = _wait_or_kill(proc, timeout_s)
        wall = time.monotonic() - t0
        status_text = _read(workdir / "exit_status").strip()
        status = int(status_text) if status_text.lstrip("-").isdigit() and not timed_out else None
        console_text = _read(workdir / "console.log") + _read(workdir / "setup.log")
        return VcanRun(self.where, status, _read(workdir / "work.log"), wall, timed_out, console_text)


def _wait_or_kill(proc: subprocess.Popen, timeout_s: float) -> bool:
    """Wait for `proc`; past the timeout kill its process group (ours: start_new_session). True if killed."""
    try:
        proc.wait(timeout=timeout_s)
        return False
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        return True


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


def find_vcan(channel: str = CHANNEL, *, create: bool = True, allow_uml: bool = True) -> Vcan:
    """The first working provider of a kernel `channel` here (module docstring).

    Raises VcanUnavailable with one line naming each provider tried and why it failed.
    Environment: QNAV_VCAN forces one provider (none: skip), QNAV_VCAN_HIDE hides some."""
    forced = os.environ.get("QNAV_VCAN", "").strip().lower()
    hidden = {h.strip().lower() for h in os.environ.get("QNAV_VCAN_HIDE", "").split(",") if h.strip()}
    if forced == "none":
        raise VcanUnavailable("QNAV_VCAN=none")
    if forced and forced not in PROVIDERS:
        raise VcanUnavailable(f"QNAV_VCAN={forced!r} unknown (one of {', '.join(PROVIDERS)}, none)")
    reasons = []
    for where in PROVIDERS:
        if (forced and where != forced) or (where != "host" and not allow_uml):
            continue
        if where in hidden:
            reasons.append(f"{where}: hidden by QNAV_VCAN_HIDE")
            continue
        why = provider_reason(where, channel, create=create)
        if why is None:
            return Vcan(where, channel)
        reasons.append(f"{where}: {why}")
    raise VcanUnavailable("; ".join(reasons) or "no provider allowed")


def main(argv: list[str] | None = None) -> int:
    """`python -m ground_station.lab.rigs.vcan [--quiet]`: each provider's verdict; exit 0 if one works."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m ground_station.lab.rigs.vcan",
                                 description="Which way to a kernel vcan0 works on this machine "
                                             "(host kernel, user-mode Linux, the project's cached UML).")
    ap.add_argument("--channel", default=CHANNEL, help="interface name (default %(default)s)")
    ap.add_argument("--no-create", action="store_true", help="do not create the interface on the host")
    args = ap.parse_args(argv)
    for where in PROVIDERS:
        why = provider_reason(where, args.channel, create=not args.no_create)
        print(f"{where:9s} {'works' if why is None else 'no: ' + why}")
    try:
        vcan = find_vcan(args.channel, create=not args.no_create)
    except VcanUnavailable as exc:
        print(f"no kernel {args.channel} here: {exc}")
        return 1
    print(f"chosen: {vcan.where}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
