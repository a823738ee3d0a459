"""Crash safety: `kill -9` of `qnav-robot` in the middle of uploads,
activations and parameter saves.

One storage directory lives through the whole run. Trials take the actions in turn and
kill at a seeded random moment inside it, measured on a calibration run of the same
action without a kill:

- upload: `qnav upload`'s code (pymavlink's MAVFTP client) puts a new policy
  version (the shipped cell policy re-issued with another policy id);
  killed during the put;
- activate: the same with activation; killed between the verified put and
  the robot confirming the new policy (rename onto active.qtab, validation,
  slot swap);
- params: PARAM_SETs back to back, each waiting for its echo; killed
  anywhere in the stream.

After every kill the storage must hold only complete versions: every policy
slot present is byte-identical to a version that was uploaded, the policy
the robot boots (active, else last-good) is the one active before the action
or the one being activated, params.json loads without a warning and equals
an acknowledged parameter state of the stream (saves are coalesced, so the
newest acknowledged sets may not have reached storage) or the one in flight,
never a mix of two states. Then the robot
is restarted on that storage, and it must report (POLICY_ID and
POLICY_CRC_HI/LO parameters) exactly the policy the check expects it to boot.
"""

from __future__ import annotations

import contextlib
import random
import tempfile
import threading
import time
from array import array
from pathlib import Path
from typing import Any

from firmware_py.mavlink.params import as_float32
from ground_station.lab.faults.common import RobotProcess, ScenarioResult, register, trials

PARAM_POOL = ("TELEM_POS_HZ", "TELEM_NAV_HZ", "GOAL_TOL_MM", "SPEED_SCALE", "MIS_TIMEOUT_MS", "MIS_RETRIES")


def policy_version(base_path: Path, policy_id: int) -> bytes:
    """The shipped cell policy's table re-issued as another version (new id)."""
    from firmware_py.policy import dump_policy, load_policy

    pol = load_policy(base_path)
    table = array("b" if pol.dtype == "int8" else "h", pol.table)
    return dump_policy(pol.encoder, table, pol.dtype, pol.scale, goals=pol.goals, cell_mm=pol.cell_mm,
                       metadata=dict(pol.metadata), policy_id=policy_id,
                       control_period_us=pol.control_period_us, map_geometry=pol.map_geometry)


class Crasher:
    """Storage, known versions and the robot process of one crash run."""

    def __init__(self, tmp: Path, seed: int) -> None:
        from firmware_py.mavlink.params import PARAMS
        from firmware_py.policy import load_policy
        from firmware_py.storage import ACTIVE_POLICY, Storage
        from ground_station.lab.rigs.lockstep import CELL_POLICY

        self.tmp = tmp
        self.storage_dir = tmp / "robot"
        self.storage = Storage(self.storage_dir)
        base = CELL_POLICY.read_bytes()
        self.storage.write_atomic(ACTIVE_POLICY, base)
        self.versions: dict[bytes, object] = {base: load_policy(base)}
        self.next_id = 0x5EED0000 + (seed & 0xFFF) * 0x100
        self.params = {d.name: d.default for d in PARAMS if not d.readonly}
        self.rng = random.Random(seed)
        self.robot: RobotProcess | None = None
        # the robot's MAVLink client (ground_station.mavlink.link.Link) while the robot runs
        self.link: Any = None

    # --- versions --------------------------------------------------------------------
    def new_version(self) -> Path:
        from firmware_py.policy import load_policy
        from ground_station.lab.rigs.lockstep import CELL_POLICY

        self.next_id += 1
        data = policy_version(CELL_POLICY, self.next_id)
        self.versions[data] = load_policy(data)
        path = self.tmp / f"v{self.next_id:08x}.qtab"
        path.write_bytes(data)
        return path

    def boot_policy(self):
        """(policy the robot will boot or None, problems) from the disk as it is."""
        from firmware_py.policy import PolicyError, load_policy
        from firmware_py.storage import ACTIVE_POLICY, LAST_GOOD_POLICY

        problems = []
        boot = None
        for slot in (ACTIVE_POLICY, LAST_GOOD_POLICY):
            path = self.storage.resolve(slot)
            if not path.exists():
                continue
            data = path.read_bytes()
            if data not in self.versions:
                problems.append(f"{slot} is not a complete uploaded version ({len(data)} B)")
                continue
            if boot is None:
                try:
                    boot = load_policy(path)
                except PolicyError as exc:
                    problems.append(f"{slot}: {exc}")
        if boot is None:
            problems.append("no bootable policy left")
        return boot, problems

    # --- robot ------------------------------------------------------------------------
    def start_robot(self) -> None:
        from ground_station.mavlink.link import Link, LinkError

        robot = self.robot = RobotProcess(self.storage_dir, log=self.tmp / "robot.log").start()
        self.link = Link(robot.url, tlog=False)
        try:
            self.link.connect(30.0)
        except LinkError:
            self.close_link()  # why it was silent: whether it exited, and its last words
            raise LinkError(4, f"robot silent for 30 s (exit {robot.returncode}): {robot.log_tail(5)}") from None

    def reported_policy(self) -> tuple[float, float, float] | None:
        got = self.link.read_params(("POLICY_ID", "POLICY_CRC_HI", "POLICY_CRC_LO"), budget_s=5.0)
        return None if None in got.values() else tuple(got.values())

    def close_link(self) -> None:
        if self.link is not None:
            with contextlib.suppress(Exception):
                self.link.close()
            self.link = None

    def stop_robot(self) -> None:
        self.close_link()
        if self.robot is not None:
            self.robot.stop()
            self.robot = None

    # --- actions ----------------------------------------------------------------------
    def upload(self, activate: bool, marks: dict) -> None:
        from ground_station.mavlink.ftp_upload import upload_policy

        local = self.new_version()
        marks["new"] = self.versions[local.read_bytes()]
        t0 = time.monotonic()
        res = upload_policy(self.link, local, f"/policies/{local.name}", activate=False, deadline_s=20,
                            attempts=2)
        marks["put_s"] = time.monotonic() - t0
        if activate:
            marks["activating"] = True
            upload_policy(self.link, local, f"/policies/{local.name}", activate=True, deadline_s=20,
                          attempts=2)
            marks["activated"] = True
        marks["total_s"] = time.monotonic() - t0
        marks["result"] = res

    def param_stream(self, n: int, marks: dict) -> None:
        from firmware_py.mavlink.params import PARAMS

        defs = {d.name: d for d in PARAMS}
        conn = self.link.conn
        marks["acked_states"] = [dict(self.params)]
        t0 = time.monotonic()
        for _ in range(n):
            name = self.rng.choice(PARAM_POOL)
            d = defs[name]
            value = self.rng.randint(d.min, min(d.max, d.min + 1000))
            marks["inflight"] = (name, value)
            for _attempt in range(5):
                conn.mav.param_set_send(self.link.sysid, self.link.compid, name.encode(),
                                        float(value), 6)
                echo = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=1.0,
                                       condition=f"PARAM_VALUE.param_id=='{name}'")
                if echo is not None and echo.param_value == as_float32(value):
                    break
            else:
                raise TimeoutError(f"no echo for {name}")
            self.params[name] = value
            marks["acked_states"].append(dict(self.params))
            marks["inflight"] = None
            marks["acked"] = marks.get("acked", 0) + 1
        marks["total_s"] = time.monotonic() - t0

    def params_problems(self, inflight, acked_states: list[dict] | None = None) -> list[str]:
        """Problems unless params.json loads cleanly and holds a state the
        stream went through: the robot echoes a PARAM_SET before its storage
        worker saves it (coalesced, as ArduPilot defers its saves), so a kill
        may leave any acknowledged state of the stream, or the one in flight
        (its save landed, its echo was lost to the kill); never a mix."""
        from firmware_py.mavlink.params import ParamStore

        store = ParamStore(self.storage_dir)
        warnings = store.load()
        if warnings:
            return [f"params after restart: {w}" for w in warnings]
        stored = {n: store.get(n) for n in self.params}
        states = list(acked_states or [])
        if inflight is not None:
            alt = dict(self.params)
            alt[inflight[0]] = inflight[1]
            states.append(alt)
        if stored == self.params or stored in states:
            self.params = stored  # what the robot restarts with is the state the next trials build on
            return []
        diff = {n: (stored[n], self.params[n]) for n in self.params if stored[n] != self.params[n]}
        return [f"params not a saved state: (stored, expected) {diff}"]


def _run_killed(target, delay_s: float, crasher: Crasher) -> tuple[bool, str]:
    """Run `target` in a thread, kill -9 the robot after `delay_s`; (finished before the kill, error)."""
    err: list[str] = []

    def body() -> None:
        try:
            target()
        except Exception as exc:  # the robot died under it: expected
            err.append(f"{type(exc).__name__}: {exc}")

    th = threading.Thread(target=body, daemon=True)
    th.start()
    th.join(delay_s)
    finished = not th.is_alive()
    assert crasher.robot is not None  # started by the caller
    crasher.robot.kill9()
    crasher.close_link()  # the client's socket goes away: a waiting recv ends
    th.join(60)
    return finished, err[0] if err else ""


@register("crash_kill9", small=3, large=50, unit="kill -9 of qnav-robot",
          what="kill -9 during upload/activation/param saves: restart boots a complete last-good version")
def crash_kill9(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    actions = {"upload": 0, "activate": 0, "params": 0}
    with tempfile.TemporaryDirectory(prefix="qnav-crash-") as tmp:
        c = Crasher(Path(tmp), seed)
        try:
            # calibration: the same actions without a kill give the windows to aim into
            c.start_robot()
            cal: dict = {}
            c.upload(True, cal)
            pcal: dict = {}
            c.param_stream(10, pcal)
            windows = {"upload": (0.0, cal["put_s"]), "activate": (cal["put_s"], cal["total_s"]),
                       "params": (0.0, pcal["total_s"])}
            res.figures["windows_s"] = {k: [round(a, 3), round(b, 3)] for k, (a, b) in windows.items()}
            for i in trials(count, progress):
                action = ("upload", "activate", "params")[i % 3]
                actions[action] += 1
                lo, hi = windows[action]
                delay = c.rng.uniform(lo, hi)
                before, problems = c.boot_policy()
                marks: dict = {}
                if action == "params":
                    finished, err = _run_killed(lambda m=marks: c.param_stream(1000, m), delay, c)
                else:
                    finished, err = _run_killed(lambda a=action, m=marks: c.upload(a == "activate", m),
                                                delay, c)
                boot, problems = c.boot_policy()
                allowed = {before.crc} | ({marks["new"].crc} if action == "activate" and "new" in marks else set())
                if boot is not None and boot.crc not in allowed:
                    problems.append(f"boots policy 0x{boot.policy_id:08x}, expected one of the last-good")
                problems += c.params_problems(marks.get("inflight") if action == "params" else None,
                                              marks.get("acked_states"))
                c.start_robot()  # the restart
                reported = c.reported_policy()
                if boot is not None:
                    want = (as_float32(boot.policy_id), float(boot.crc >> 16), float(boot.crc & 0xFFFF))
                    if reported != want:
                        problems.append(f"restarted robot reports {reported}, disk says {want}")
                if action == "activate" and marks.get("activating") and not marks.get("activated"):
                    res.figures["killed_mid_activation"] = res.figures.get("killed_mid_activation", 0) + 1
                if finished:  # still a valid crash (after the action), but not inside it
                    res.figures["ended_before_kill"] = res.figures.get("ended_before_kill", 0) + 1
                res.check(problems, f"kill {i} during {action} at {delay:.3f} s ({err or 'no error'})")
        finally:
            c.stop_robot()
    res.figures["actions"] = actions
