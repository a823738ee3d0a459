"""Issue 43 findings 5-8: what the robot keeps on its storage and what the operator's tools write, one
scenario each, on real parts.

- `map_refused_stays_refused` (finding 5): the real Controller behind the real FtpServer; a map
  uploaded and renamed onto /maps/active.map while the map worker (the real one, held at a seeded
  moment by a gate around its localiser build) is slower than the server's activation timeout, or
  just as fast (both released in a race). The verdict the client gets is the robot's state: a NAK
  ("map refused: activation not ready") leaves the old map in the controller and /maps/active.map
  untouched for good (checked after the worker has ended); an ACK has the new one in both.
- `log_readonly_over_ftp` (finding 6): the real OnboardLog writing records into a real Storage root
  while seeded hostile FTP requests from any system id (RemoveFile, TruncateFile, CreateFile,
  OpenFileWO + WriteFile + TerminateSession, Rename into and out of /logs, RemoveDirectory,
  CreateDirectory, with path spellings such as `logs//./robot.log`) each get NAK FileProtected (9);
  robot.log keeps its inode and never shrinks, and at the end holds every record written, in order.
  Reading and listing /logs (what `qnav log pull` does) stay answered.
- `log_pull_plain_names` (finding 7): a real `qnav log pull` process against a MAVLink peer on UDP
  loopback (pymavlink, system 1, the real FtpServer over a storage whose /logs listing carries a
  hostile name: `../x`, an absolute path, `a/b`, `..`, `.`, an empty name, a backslash, also given
  on the command line): one stderr line naming the bad name, exit 2, and nothing written, inside
  --out or outside it.
- `profile_deep_nesting` (finding 8): `qnav-robot --profile` and `qnav-sim --profile` processes with
  a profile nested 300 .. 20000 deep (arrays or inline tables, at the top level or under a known
  key): one stderr line naming the file, exit 2 (tomllib's RecursionError was a traceback, exit 1).
"""

from __future__ import annotations

import contextlib
import os
import random
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from ground_station.lab.faults.common import ScenarioResult, register, trials
from ground_station.lab.faults.hostile_holes import _Ftp

FILE_PROTECTED = 9  # firmware_py.mavlink.ftp_server.Nak.FILE_PROTECTED


# --- finding 5: a refused map stays refused ------------------------------------------------------------

def _map_text(width: int, height: int, rng: random.Random) -> str:
    rows = ["@" * width] + ["@" + "".join("@" if rng.random() < 0.1 else "." for _ in range(width - 2)) + "@"
                            for _ in range(height - 2)] + ["@" * width]
    return f"type octile\nheight {height}\nwidth {width}\nmap\n" + "\n".join(rows) + "\n"


def _put(ftp: _Ftp, owner: tuple[int, int], path: str, data: bytes) -> bool:
    from firmware_py.mavlink.ftp_server import Op

    if ftp.is_nak(ftp.req(owner, Op.CREATE_FILE, path.encode())):
        return False
    for off in range(0, len(data), 200):
        if ftp.is_nak(ftp.req(owner, Op.WRITE_FILE, data[off:off + 200], 0, off)):
            return False
    return not ftp.is_nak(ftp.req(owner, Op.TERMINATE_SESSION))


@register("map_refused_stays_refused", small=6, large=200, unit="map activations (FTP Rename onto /maps/active.map)",
          what="a map activation answered 'map refused' (activation timeout) never becomes active; an ACKed one is")
def map_refused_stays_refused(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    from firmware_py import policy as fmt
    from firmware_py.control.controller import Controller
    from firmware_py.mapdata import describe, grid_from_map_file
    from firmware_py.mavlink.ftp_server import FtpServer, Op, parse
    from firmware_py.shipped_policies import resolve_policy_spec
    from firmware_py.storage import ACTIVE_MAP, Storage
    from firmware_py.vehicle import VehicleConfig

    rng = random.Random(seed)
    sector = fmt.load_policy(resolve_policy_spec("policies:sector"))
    counts = {"late": 0, "early": 0, "race": 0}
    verdicts = {"refused": 0, "active": 0}
    race = {"refused": 0, "active": 0}  # the verdicts of the 'race' timing alone
    late_finishes = 0  # workers that finished after the server had answered "refused"
    owner = (255, 190)
    for i in trials(count, progress):
        # the first three trials cover each timing, the rest are seeded
        mode = ("late", "early", "race")[i] if i < 3 else rng.choice(("late", "late", "early", "race"))
        counts[mode] += 1
        problems: list[str] = []
        with tempfile.TemporaryDirectory(prefix="qnav-maprefuse-") as tmp:
            ctrl = Controller(VehicleConfig(), sector)
            old_text = _map_text(rng.randint(8, 14), rng.randint(8, 14), rng)
            (Path(tmp) / "old.map").write_text(old_text)
            assert ctrl.set_robot_map(grid_from_map_file(str(Path(tmp) / "old.map"), ctrl.cfg.cell_size_mm))[0]
            old_map = ctrl.robot_map
            timeout_us = rng.randint(1, 20) * 1_000_000
            pendings: list[Any] = []

            def begin(path: str, pendings: list[Any] = pendings, ctrl: Any = ctrl) -> Any:
                got = ctrl.begin_map_activation(path)
                if not isinstance(got, tuple):
                    pendings.append(got)
                return got

            storage = Storage(Path(tmp) / "root", quota_bytes=2_000_000)
            storage.write_atomic(ACTIVE_MAP, old_text.encode())
            server = FtpServer(storage, activate_map=begin, activation_timeout_us=timeout_us)
            ftp = _Ftp(server)
            gate, built = threading.Event(), threading.Event()
            real_build = ctrl._new_localiser

            def held_build(pol: Any, gate: threading.Event = gate, built: threading.Event = built,
                           real_build: Any = real_build) -> Any:
                loc = real_build(pol)  # the real build, then held until the scenario says
                built.set()
                gate.wait(30)
                return loc

            ctrl._new_localiser = held_build  # type: ignore[method-assign]
            new_text = _map_text(rng.randint(15, 40), rng.randint(15, 40), rng)
            if not _put(ftp, owner, "/maps/new.map", new_text.encode()):
                problems.append("upload of the map refused")
            t0 = ftp.now
            replies = ftp.req(owner, Op.RENAME, f"/maps/new.map\0{ACTIVE_MAP}\0".encode())
            answered: list = list(replies)  # a map's localiser is built on the worker: no reply yet
            if answered:
                problems.append(f"rename answered at once: {answered}")
            if mode == "late":  # the server's timeout first, then the worker ends
                answered += [parse(r) for _o, r in server.poll(t0 + timeout_us + 1)]
                gate.set()
            elif mode == "early":  # the worker ends, then the server's poll
                gate.set()
                deadline = time.monotonic() + 30
                while pendings and pendings[0].result() is None and time.monotonic() < deadline:
                    time.sleep(0.002)
                answered += [parse(r) for _o, r in server.poll(t0 + 1)]
            else:  # both at once: the built map's swap is let go as the server times out
                built.wait(30)
                gate.set()
                time.sleep(rng.random() * 0.0005)  # 0-0.5 ms: either side may come first
                answered += [parse(r) for _o, r in server.poll(t0 + timeout_us + 1)]
            deadline = time.monotonic() + 30
            while pendings and pendings[0].result() is None and time.monotonic() < deadline:
                time.sleep(0.002)  # the worker's end, whatever the verdict
            for _ in range(100):  # a reply left for a later poll (the worker was committing)
                if answered:
                    break
                answered += [parse(r) for _o, r in server.poll(t0 + timeout_us + 2)]
                time.sleep(0.005)
            time.sleep(0.01)
            ctrl._new_localiser = real_build  # type: ignore[method-assign]
            texts = [t for _s, t in server.drain_texts()]
            if not pendings:
                problems.append("the map activation was not handed to the worker")
            elif pendings[0].result() is None:
                problems.append("the map worker did not end within 30 s")
            if len(answered) != 1:
                problems.append(f"{len(answered)} replies to the rename")
            else:
                nak = answered[0][2] == Op.NAK
                if mode == "race":
                    race["refused" if nak else "active"] += 1
                on_disk = storage.read_bytes(ACTIVE_MAP).decode()
                if nak:
                    verdicts["refused"] += 1
                    if pendings and pendings[0].result() is not None and mode != "early":
                        late_finishes += 1
                    if ctrl.robot_map != old_map:
                        problems.append(f"answered 'map refused' ({'; '.join(texts)}) but the controller runs "
                                        f"{describe(ctrl.robot_map) if ctrl.robot_map else None} "
                                        f"(the old one: {describe(old_map)})")
                    if on_disk != old_text:
                        problems.append("answered 'map refused' but /maps/active.map changed")
                else:
                    verdicts["active"] += 1
                    if ctrl.robot_map == old_map:
                        problems.append("answered ACK but the old map is still the controller's")
                    if on_disk != new_text:
                        problems.append("answered ACK but /maps/active.map is not the uploaded map")
                if mode == "late" and not nak:
                    problems.append("the activation was ACKed although the worker was held past the timeout")
                if mode == "early" and nak:
                    problems.append(f"refused although the worker had finished in time: {texts}")
        res.check(problems, f"seed {seed}/{i} {mode} timeout {timeout_us / 1e6:g} s")
    res.figures.update({"timings": counts, "verdicts": verdicts, "race_verdicts": race,
                        "refused_then_worker_finished": late_finishes})


# --- finding 6: the onboard log is read-only over FTP --------------------------------------------------

def _spell(rng: random.Random, path: str) -> str:
    """`path` as a hostile client may spell it (the server normalises)."""
    return rng.choice((path, path.lstrip("/"), path.replace("/", "//"), path.replace("/logs/", "/logs/./"),
                       "/./" + path.lstrip("/"), path + ("/" if path.endswith("logs") else "")))


@register("log_readonly_over_ftp", small=60, large=3000, unit="hostile FTP requests on /logs",
          what="every write, remove, truncate, rename or mkdir in /logs from any system id is NAK FileProtected; "
               "robot.log keeps every record; reading and listing /logs still work")
def log_readonly_over_ftp(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    import logging

    from firmware_py.mavlink.ftp_server import FtpServer, Op
    from firmware_py.onboard_log import OnboardLog
    from firmware_py.storage import Storage

    rng = random.Random(seed)
    kinds: dict[str, int] = {}
    reads = 0
    with tempfile.TemporaryDirectory(prefix="qnav-logro-") as tmp:
        root = Path(tmp) / "root"
        storage = Storage(root, quota_bytes=8_000_000)
        onboard = OnboardLog(root, max_bytes=6_000_000, period_s=3600).start()
        log = logging.getLogger("qnav.controller")
        ftp = _Ftp(FtpServer(storage))
        path = root / "logs" / "robot.log"
        log.info("record %d", 0)
        _wait_for(lambda: path.exists() and b"record 0\n" in path.read_bytes())
        inode, size = path.stat().st_ino, path.stat().st_size
        storage.write_atomic("/policies/src.bin", b"not a log\n")
        written = 1
        stopped = False
        try:
            for i in trials(count, progress):
                owner = (rng.randint(1, 255), rng.randint(0, 255))
                sid = rng.randrange(256)
                kind = rng.choice(("remove", "truncate", "create", "open_wo", "rename_out", "rename_in",
                                   "rename_in_new", "rmdir", "mkdir", "create_new", "remove_rotated"))
                kinds[kind] = kinds.get(kind, 0) + 1
                target = _spell(rng, "/logs/robot.log")
                replies: list = []
                if kind == "remove":
                    replies = ftp.req(owner, Op.REMOVE_FILE, target.encode())
                elif kind == "remove_rotated":
                    replies = ftp.req(owner, Op.REMOVE_FILE, _spell(rng, "/logs/robot.log.1").encode())
                elif kind == "truncate":
                    replies = ftp.req(owner, Op.TRUNCATE_FILE, target.encode(), sid, rng.choice((0, 1, size // 2)))
                elif kind in ("create", "open_wo", "create_new"):
                    op = Op.CREATE_FILE if kind != "open_wo" else Op.OPEN_FILE_WO
                    name = target if kind != "create_new" else _spell(rng, "/logs/evil.log")
                    replies = ftp.req(owner, op, name.encode(), sid)
                    ftp.req(owner, Op.WRITE_FILE, b"forged\n", sid, 0)
                    ftp.req(owner, Op.TERMINATE_SESSION, b"", sid)
                elif kind == "rename_out":
                    replies = ftp.req(owner, Op.RENAME, f"{target}\0/policies/stolen\0".encode())
                elif kind == "rename_in":
                    replies = ftp.req(owner, Op.RENAME, f"/policies/src.bin\0{target}\0".encode())
                elif kind == "rename_in_new":
                    replies = ftp.req(owner, Op.RENAME, f"/policies/src.bin\0{_spell(rng, '/logs/new.log')}\0".encode())
                elif kind == "rmdir":
                    replies = ftp.req(owner, Op.REMOVE_DIRECTORY, _spell(rng, "/logs").encode())
                else:  # mkdir
                    replies = ftp.req(owner, Op.CREATE_DIRECTORY, _spell(rng, "/logs/sub").encode())
                problems: list[str] = []
                if not ftp.is_nak(replies, FILE_PROTECTED):
                    got = "no reply" if not replies else f"opcode {replies[0][2]} data {replies[0][7][:2]!r}"
                    problems.append(f"{kind} {target!r} from {owner}: {got}, not NAK FileProtected")
                log.info("record %d", written)
                written += 1
                if not path.exists():
                    problems.append("robot.log is gone")
                else:
                    st = path.stat()
                    if st.st_ino != inode:
                        problems.append("robot.log was replaced (another inode)")
                    if st.st_size < size:
                        problems.append(f"robot.log shrank from {size} to {st.st_size} bytes")
                    inode, size = st.st_ino, max(size, st.st_size)
                names = {e.name for e in storage.listdir("/logs")}
                if names - {"robot.log"}:
                    problems.append(f"/logs holds {sorted(names - {'robot.log'})}")
                if i % 10 == 0:  # what `qnav log pull` does: list, CRC, open, read
                    reads += 1
                    lst = ftp.req(owner, Op.LIST_DIRECTORY, b"/logs", 7)
                    crc = ftp.req(owner, Op.CALC_FILE_CRC32, b"/logs/robot.log", 7)
                    opened = ftp.req(owner, Op.OPEN_FILE_RO, b"/logs/robot.log", 7)
                    read = ftp.req(owner, Op.READ_FILE, b"", 7, 0)
                    ftp.req(owner, Op.TERMINATE_SESSION, b"", 7)
                    if any(ftp.is_nak(r) or not r for r in (lst, crc, opened, read)):
                        problems.append("reading or listing /logs was refused")
                    elif b"robot.log" not in lst[0][7] or not read[0][7].strip():
                        problems.append("the listing or the read did not show robot.log")
                ftp.now += 100_000
                if i == count - 1:  # the last trial also checks the whole log: every record, in order
                    onboard.stop()
                    stopped = True
                    text = path.read_text() if path.exists() else ""
                    records = [int(line.rsplit(" ", 1)[1]) for line in text.splitlines() if " record " in line]
                    if records != list(range(written)):
                        missing = sorted(set(range(written)) - set(records))
                        problems.append(f"robot.log holds {len(records)} of {written} records "
                                        f"(first missing: {missing[:5]})")
                res.check(problems, f"seed {seed}/{i} {kind}")
        finally:
            if not stopped:
                onboard.stop()
        text = path.read_text() if path.exists() else ""
        records = [int(line.rsplit(" ", 1)[1]) for line in text.splitlines() if " record " in line]
        res.figures.update({"requests": kinds, "reads_and_listings": reads, "records_written": written,
                            "records_in_log": len(records), "log_bytes": len(text.encode())})


def _wait_for(cond: Any, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


# --- finding 7: `qnav log pull` writes only plain names into --out -----------------------------------------

class _HostileRobot:
    """System 1 on UDP loopback (pymavlink): HEARTBEATs and the real FtpServer, over a storage whose
    /logs listing is `listing` and whose every /logs/<name> read gives `content`."""

    def __init__(self, port: int, listing: list[str], content: bytes, tmp: Path) -> None:
        from firmware_py.mavlink.dialect import NAME as DIALECT
        from firmware_py.mavlink.ftp_server import FtpServer
        from firmware_py.storage import Entry, Storage
        from ground_station.mavlink.link import mavutil

        body = tmp / "served.log"
        body.write_bytes(content)

        class HostileStorage(Storage):
            def listdir(self, ftp_path: str) -> list[Entry]:
                if ftp_path.strip("/") == "logs":
                    return [Entry(n, False, len(content), 0) for n in listing]
                return super().listdir(ftp_path)

            def open_read(self, ftp_path: str) -> tuple[int, int]:
                if ftp_path.startswith("/logs/"):
                    fd = os.open(body, os.O_RDONLY)
                    return fd, os.fstat(fd).st_size
                return super().open_read(ftp_path)

        self.server = FtpServer(HostileStorage(tmp / "robot-root"))
        self.conn = mavutil().mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=1, source_component=1,
                                                 dialect=DIALECT)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="hostile-robot", daemon=True)

    def __enter__(self) -> _HostileRobot:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)
        with contextlib.suppress(Exception):
            self.conn.close()

    def _run(self) -> None:
        m = self.conn.mav
        last_beat = 0.0
        t0 = time.monotonic()
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            now = time.monotonic()
            if msg is not None and msg.get_type() == "FILE_TRANSFER_PROTOCOL" and msg.target_system in (0, 1):
                src = (msg.get_srcSystem(), msg.get_srcComponent())
                for reply in self.server.handle(bytes(msg.payload), int((now - t0) * 1e6), src):
                    m.file_transfer_protocol_send(0, src[0], src[1], list(reply.ljust(251, b"\0")))
            if msg is not None and now - last_beat > 0.5:  # once the peer's address is known
                m.heartbeat_send(10, 0, 0, 0, 3)  # MAV_TYPE_GROUND_ROVER, MAV_AUTOPILOT_GENERIC, STANDBY
                last_beat = now


def _tree(top: Path) -> dict[str, int]:
    out = {}
    for dirpath, dirs, files in os.walk(top):
        for name in files + dirs:
            p = Path(dirpath) / name
            out[str(p.relative_to(top))] = p.stat().st_size if p.is_file() else -1
    return out


def _refusal(argv: list[Any], cwd: Path, problems: list[str]) -> tuple[int, str]:
    """Run `argv` in `cwd`, 90 s at most (exit -9 then), which must refuse its input: a problem
    unless it exits 2. (Its exit status, its stderr.)"""
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=90, cwd=cwd, stdin=subprocess.DEVNULL)
        rc, err = proc.returncode, proc.stderr
    except subprocess.TimeoutExpired:
        rc, err = -9, "timed out after 90 s"
    if rc != 2:
        problems.append(f"exit {rc}, not 2")
    return rc, err


@register("log_pull_plain_names", small=3, large=30, unit="`qnav log pull` runs against a hostile listing",
          what="a log name with a separator, '..', '.', or empty is refused in one line, exit 2; nothing written")
def log_pull_plain_names(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    from ground_station.processes import program_argv
    from ground_station.subprocs import free_udp_port

    rng = random.Random(seed)
    outcomes: dict[str, int] = {}
    for i in trials(count, progress):
        problems: list[str] = []
        with tempfile.TemporaryDirectory(prefix="qnav-logpull-") as tmp_s:
            tmp = Path(tmp_s)
            out = tmp / "a" / "b" / "out"
            (tmp / "abs").mkdir()
            (tmp / "a" / "b").mkdir(parents=True)
            # the ones that escaped --out first (the test's small count), then every shape
            bad = ["../escaped.log", str(tmp / "abs" / "escaped.log"), "../../escaped.log", "sub/x.log", "..", ".",
                   "", "a\\b.log", "../" * 12 + "tmp/escaped.log"][i % 9 if i < 9 else rng.randrange(9)]
            listing = [bad, "robot.log"] if rng.random() < 0.5 else ["robot.log", bad]
            on_cli = i >= 3 and bad != "" and rng.random() < 0.3  # `qnav log pull NAME` names it itself
            content = rng.randbytes(rng.randint(0, 600)).replace(b"\0", b"x")
            before = _tree(tmp)
            port = free_udp_port()
            argv = [*program_argv("ground_station.cli:main", "qnav"), "log", "pull", "--mavlink",
                    f"udpout:127.0.0.1:{port}", "--no-tlog", "--timeout", "15", "--out", str(out),
                    *([bad] if on_cli else [])]
            with _HostileRobot(port, listing, content, tmp):
                rc, err = _refusal(argv, tmp, problems)
            after = _tree(tmp)
            new = sorted(set(after) - set(before) - {"served.log", "robot-root", "robot-root/policies",
                                                     "robot-root/params", "robot-root/maps"})
            outside = [p for p in new if not p.startswith("a/b/out")]
            lines = err.strip().splitlines()
            outcomes[f"exit {rc}"] = outcomes.get(f"exit {rc}", 0) + 1
            if len(lines) != 1:
                problems.append(f"stderr has {len(lines)} lines: {err.strip()[-200:]!r}")
            elif repr(bad) not in lines[0]:
                problems.append(f"stderr does not name {bad!r}: {lines[0][:200]!r}")
            if outside:
                problems.append(f"written outside --out: {outside}")
            inside = [p for p in new if p.startswith("a/b/out/")]
            if inside:
                problems.append(f"written inside --out although refused: {inside}")
        res.check(problems, f"seed {seed}/{i} name {bad!r}{' (on the command line)' if on_cli else ''}")
    res.figures["exit_codes"] = outcomes


# --- finding 8: a deeply nested profile is refused in one line -----------------------------------------

def _nested_profile(rng: random.Random, depth: int) -> tuple[str, str]:
    """A profile nested `depth` deep: (its text, what shape)."""
    shape = rng.choice(("array", "table"))
    if shape == "array":
        value = "[" * depth + "1" + "]" * depth
    else:
        value = "{ a = " * depth + "1" + " }" * depth
    where = rng.choice(("top", "key"))
    text = f"x = {value}\n" if where == "top" else f"[geometry]\nwheel_base_mm = {value}\n"
    return text, f"{shape} at {where}"


@register("profile_deep_nesting", small=4, large=40, unit="qnav-robot / qnav-sim runs with a nested --profile",
          what="a profile nested 300..20000 deep (arrays or inline tables): one stderr line naming it, exit 2")
def profile_deep_nesting(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    from ground_station.processes import qnav_robot, qnav_sim

    rng = random.Random(seed)
    outcomes: dict[str, int] = {}
    with tempfile.TemporaryDirectory(prefix="qnav-deepprof-") as tmp_s:
        tmp = Path(tmp_s)
        for i in trials(count, progress):
            program = ("qnav-robot", "qnav-sim")[i % 2]
            depth = 5000 if i < 2 else rng.choice((300, 1000, 5000, 20000))
            text, shape = _nested_profile(rng, depth)
            prof = tmp / f"deep-{i}.toml"
            prof.write_text(text)
            argv = (qnav_robot("--profile", prof, "--can", "virtual:deep-profile", "-q") if program == "qnav-robot"
                    else qnav_sim("--map", "paper10", "--profile", prof))
            problems: list[str] = []
            rc, err = _refusal(argv, tmp, problems)
            lines = err.strip().splitlines()
            key = f"{program} exit {rc}"
            outcomes[key] = outcomes.get(key, 0) + 1
            if len(lines) != 1:
                problems.append(f"stderr has {len(lines)} lines (last: {lines[-1][:120] if lines else ''!r})")
            elif str(prof) not in lines[0]:
                problems.append(f"stderr does not name the file: {lines[0][:200]!r}")
            res.check(problems, f"seed {seed}/{i} {program} depth {depth} {shape}")
    res.figures["outcomes"] = outcomes
