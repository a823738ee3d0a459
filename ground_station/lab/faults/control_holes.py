"""Issue 43 findings 1 and 3: only the operator's GCS steers, and a parameter-list flood cannot
delay Hold. One scenario each, plus the flood again on real processes.

Lockstep (`rigs.lockstep.LockstepRig`: the pymunk plant and the real RobotNode + Controller on a
python-can virtual bus; the real `MavNode` polled after every tick, hostile_holes._PolledNode;
frames packed by pymavlink and parsed by the robot's parser):

- `mav_foreign_control` (finding 1): the operator (system 255) arms and selects Manual; for 3 s
  of robot time another sender steers every tick, one way per trial: MANUAL_CONTROL x=600 or an
  RC override from system 77, the same addressed to every system (target 0) from 255 itself,
  SET_MODE Guided + a goal from 77, PARAM_SET SYSID_MYGCS=77 then sticks from 77. Holds when
  no wheel command is non-zero through the attack, the mode and SYSID_MYGCS are unchanged, the
  refusals were summarised in at most one STATUSTEXT a second, and the operator's own sticks
  then drive the wheels (so nothing passes only because nothing could steer).
- `mav_param_list_flood` (finding 3): the operator drives in Manual (sticks every tick); system
  88 sends 75 PARAM_REQUEST_LIST a tick (1,500/s at 20 Hz); at a seeded moment the operator
  sends SET_MODE Hold (or stops the sticks: the deadman). Holds when Hold is ACKed ACCEPTED in
  the answers to that very poll and the next command is zero (deadman: zero within 0.5 s + one
  period of the last stick), and the robot sent at most RATE_HZ PARAM_VALUEs a second (+ one
  burst) through the flood: the amplification was the cause (31 answers a request before).

Paced HIL, real processes (floods.driving_robot: hub + `qnav-sim --realtime` + `qnav-robot
--sim-clock`, MAVLink on UDP loopback):

- `param_list_flood_hil`: while the robot drives its tour, system 88 floods 1,500
  PARAM_REQUEST_LIST a second; after 1-2 s of it the operator's `Link` (255) sends SET_MODE Hold
  once. Holds when that first SET_MODE is ACKed (1 s) and the robot's HOLD transition comes
  within 0.5 s of robot time of the newest robot stamp seen before the send.
"""

from __future__ import annotations

import random
import tempfile
import threading
import time
from contextlib import suppress
from pathlib import Path
from typing import Any

from firmware_py.mavlink.param_stream import BURST, RATE_HZ
from firmware_py.vehicle import CtrlState, Mode
from ground_station.lab.faults.common import ScenarioResult, register, trials
from ground_station.lab.faults.hostile_holes import FOREIGN_GCS, GCS, _PolledNode
from ground_station.lab.faults.runtime_holes import _sector_rig
from ground_station.lab.rigs.lockstep import PERIOD_US

ATTACKS = ("manual_control sys77", "rc_override sys77", "manual_control broadcast", "rc_override broadcast",
           "mode+goal sys77", "param_set MYGCS then sticks sys77")
ATTACK_US = 3_000_000
FLOOD_PER_TICK = 75  # x 20 Hz = 1,500 requests a second
FLOOD_SYSID = 88
DEADMAN_US = 500_000
SPIN_R = 400  # the operator's sticks in the checks: a turn on the spot, which no wall stops


class _Operator:
    """Frames from one sender into the polled node, packed by pymavlink."""

    def __init__(self, polled: _PolledNode, sysid: int, compid: int) -> None:
        self.polled = polled
        self.codec = polled.m.MAVLink(None, sysid, compid)

    def send(self, msg: Any) -> None:
        self.polled.inbox.put(bytes(msg.pack(self.codec)))

    def beat(self) -> None:
        m = self.polled.m
        self.send(self.codec.heartbeat_encode(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0))


def _armed_manual(rig, polled: _PolledNode, op: _Operator) -> list[str]:
    m = polled.m
    op.beat()
    rig.run_until(rig.time_us + 3 * PERIOD_US)
    op.send(op.codec.command_long_encode(1, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    rig.tick()
    op.send(op.codec.set_mode_encode(1, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(Mode.MANUAL)))
    rig.tick()
    rig.tick()
    st = rig.ctrl.status()
    return [] if st.armed and st.mode == Mode.MANUAL else [f"setup: armed {st.armed}, mode {st.mode}"]


def _attack_frames(attack: str, op: _Operator, foreign: _Operator, gm_goal: tuple[float, float]) -> list[tuple[_Operator, Any]]:
    m, fc, oc = op.polled.m, foreign.codec, op.codec
    if attack == "manual_control sys77":
        return [(foreign, fc.manual_control_encode(1, 600, 0, 500, 0, 0))]
    if attack == "rc_override sys77":
        return [(foreign, fc.rc_channels_override_encode(1, 1, 1500, 0, 1900, 0, 0, 0, 0, 0))]
    if attack == "manual_control broadcast":
        return [(op, oc.manual_control_encode(0, 600, 0, 500, 0, 0))]
    if attack == "rc_override broadcast":
        return [(op, oc.rc_channels_override_encode(0, 0, 1500, 0, 1900, 0, 0, 0, 0, 0))]
    if attack == "mode+goal sys77":
        return [(foreign, fc.set_mode_encode(1, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(Mode.GUIDED))),
                (foreign, fc.set_position_target_local_ned_encode(0, 1, 1, m.MAV_FRAME_LOCAL_NED, 0b110111111000,
                                                                  gm_goal[0], gm_goal[1], 0, 0, 0, 0, 0, 0, 0, 0, 0))]
    return [(foreign, fc.param_set_encode(1, 1, b"SYSID_MYGCS", float(FOREIGN_GCS[0]), m.MAV_PARAM_TYPE_INT32)),
            (foreign, fc.manual_control_encode(1, 600, 0, 500, 0, 0))]


@register("mav_foreign_control", small=6, large=60, unit="attacks (3 s each)",
          what="another system's sticks / RC override / mode+goal / PARAM_SET, or broadcast sticks, while the "
               "operator has the robot armed in Manual -> 0 non-zero wheel commands; the operator still steers")
def foreign_control(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    moving_by_attack: dict[str, int] = {}
    refusal_texts = 0
    for i in trials(count, progress):
        attack = ATTACKS[(seed + i) % len(ATTACKS)]
        rng, rig = _sector_rig(seed * 7919 + 43000 + i, with_goal=False)
        problems: list[str] = []
        with rig:
            polled = _PolledNode(rig, 5000)
            op, foreign = _Operator(polled, *GCS), _Operator(polled, *FOREIGN_GCS)
            problems += _armed_manual(rig, polled, op)
            st = rig.ctrl.status()
            goal = ((st.x_mm + 600) / 1000, (st.y_mm) / 1000)
            t0, texts0 = rig.time_us, len(polled.texts)
            while rig.time_us < t0 + ATTACK_US:
                if (rig.time_us - t0) % 1_000_000 < PERIOD_US:
                    op.beat()
                for who, msg in _attack_frames(attack, op, foreign, goal):
                    who.send(msg)
                rig.tick()
            moving = sum(1 for t, left, right, _ in rig.commands if t > t0 and (left or right))
            moving_by_attack[attack] = moving_by_attack.get(attack, 0) + moving
            texts = [t for t in polled.texts[texts0:] if t.startswith("control refused")]
            refusal_texts += len(texts)
            if moving:
                problems.append(f"{moving} non-zero wheel commands in {ATTACK_US // PERIOD_US} ticks")
            st = rig.ctrl.status()
            if st.mode != Mode.MANUAL:
                problems.append(f"mode changed to {st.mode.name}")
            if polled.node.params.get("SYSID_MYGCS") != GCS[0]:
                problems.append(f"SYSID_MYGCS became {polled.node.params.get('SYSID_MYGCS')}")
            if len(texts) > ATTACK_US // 1_000_000 + 1:
                problems.append(f"{len(texts)} refusal STATUSTEXTs in {ATTACK_US / 1e6:.0f} s (one a second at most)")
            if not texts:
                problems.append("the refusals were not reported")
            t1 = rig.time_us  # the positive control: the operator's own sticks drive
            while rig.time_us < t1 + 500_000:  # a turn on the spot: no wall stops it
                op.send(op.codec.manual_control_encode(1, 0, 0, 500, SPIN_R, 0))
                rig.tick()
            if not any(left and right for t, left, right, _ in rig.commands if t > t1):
                problems.append("the operator's own sticks did not drive the wheels")
            problems += [f"poll raised: {e}" for e in polled.errors]
        res.check(problems, f"seed {seed}/{i} {attack}")
    res.figures["non_zero_commands_by_attack"] = moving_by_attack
    res.figures["refusal_statustexts"] = refusal_texts


@register("mav_param_list_flood", small=2, large=20, unit="episodes",
          what="1,500 PARAM_REQUEST_LIST/s from another system while the operator drives in Manual: Hold ACKed "
               "at once and the next command zero / deadman within 0.5 s; PARAM_VALUEs within the stream rate")
def param_list_flood(res: ScenarioResult, count: int, seed: int, progress: Any) -> None:
    worst_rate = 0.0
    values_per_request: list[float] = []
    worst_deadman_us = 0
    for i in trials(count, progress):
        stop = ("set_mode hold", "deadman")[(seed + i) % 2]
        rng, rig = _sector_rig(seed * 7919 + 44000 + i, with_goal=False)
        problems: list[str] = []
        with rig:
            polled = _PolledNode(rig, 5000)
            op, flooder = _Operator(polled, *GCS), _Operator(polled, FLOOD_SYSID, 190)
            values: list[tuple[int, int]] = []  # (robot time, PARAM_VALUEs sent in that poll)
            acks: list[tuple[int, int, int]] = []  # (robot time, command, result)

            node_handle, node_tick = polled.node.handle, polled.node.tick

            def handle(msg, now_us, node_handle=node_handle, values=values, acks=acks):
                out = node_handle(msg, now_us)
                _record(out, now_us, values, acks)
                return out

            def tick(now_us, node_tick=node_tick, values=values, acks=acks):
                out = node_tick(now_us)
                _record(out, now_us, values, acks)
                return out

            polled.node.handle, polled.node.tick = handle, tick  # type: ignore[method-assign]
            problems += _armed_manual(rig, polled, op)
            t0 = rig.time_us
            t_stop = t0 + 1_000_000 + rng.randrange(0, 1_000_000, PERIOD_US)
            requests = 0
            last_stick = None
            while rig.time_us < t_stop:
                if (rig.time_us - t0) % 1_000_000 < PERIOD_US:
                    op.beat()
                op.send(op.codec.manual_control_encode(1, 0, 0, 500, SPIN_R, 0))
                last_stick = rig.time_us
                for _ in range(FLOOD_PER_TICK):
                    flooder.send(flooder.codec.param_request_list_encode(1, 1))
                requests += FLOOD_PER_TICK
                rig.tick()
            if not any(left and right for t, left, right, _ in rig.commands if t > t0):
                problems.append("setup: the sticks did not drive")
            m = polled.m
            if stop == "set_mode hold":
                op.send(op.codec.set_mode_encode(1, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(Mode.HOLD)))
            for _ in range(int(1.5 * DEADMAN_US) // PERIOD_US):
                for _ in range(FLOOD_PER_TICK):
                    flooder.send(flooder.codec.param_request_list_encode(1, 1))
                requests += FLOOD_PER_TICK
                rig.tick()
            handled = t_stop  # the poll after the tick that ended at t_stop handled the last frames
            if stop == "set_mode hold":
                got = [a for a in acks if a[1] == m.MAV_CMD_DO_SET_MODE]
                if not got or got[0][2] != m.MAV_RESULT_ACCEPTED or got[0][0] > handled:
                    problems.append(f"Hold not ACKed ACCEPTED in the poll that got it: {got[:2]}")
                late = [(t, left, right) for t, left, right, _ in rig.commands if t > handled + PERIOD_US
                        and (left or right)]
                if late:
                    problems.append(f"wheels still turning after Hold: {late[:2]}")
                if rig.ctrl.status().mode != Mode.HOLD:
                    problems.append(f"mode {rig.ctrl.status().mode.name}, not HOLD")
            else:
                assert last_stick is not None
                moving = [t for t, left, right, _ in rig.commands if t > last_stick and (left or right)]
                stopped_after = (max(moving) - last_stick + PERIOD_US) if moving else 0
                worst_deadman_us = max(worst_deadman_us, stopped_after)
                if stopped_after > DEADMAN_US + PERIOD_US:
                    problems.append(f"deadman stopped the wheels {stopped_after / 1000:.0f} ms after the last stick")
            t_first, t_last = t0, rig.time_us
            sent = sum(n for t, n in values if t_first <= t <= t_last)
            seconds = (t_last - t_first) / 1e6
            rate = (sent - BURST) / seconds if seconds > 0 else 0.0
            worst_rate = max(worst_rate, rate)
            values_per_request.append(sent / max(1, requests))
            if rate > RATE_HZ:
                problems.append(f"{sent} PARAM_VALUEs in {seconds:.1f} s for {requests} requests "
                                f"({rate:.0f}/s, stream rate {RATE_HZ}/s)")
            if rig.ctrl.state == CtrlState.FAULT:
                problems.append("FAULT")
            problems += [f"poll raised: {e}" for e in polled.errors]
        res.check(problems, f"seed {seed}/{i} {stop}")
    res.figures["param_values_per_s_max"] = round(worst_rate, 1)
    res.figures["param_values_per_request"] = round(max(values_per_request, default=0.0), 3)
    res.figures["deadman_stop_ms_max"] = worst_deadman_us / 1000


def _record(out: list, now_us: int, values: list[tuple[int, int]], acks: list[tuple[int, int, int]]) -> None:
    n = 0
    for msg in out:
        kind = msg.get_type()
        if kind == "PARAM_VALUE":
            n += 1
        elif kind == "COMMAND_ACK":
            acks.append((now_us, msg.command, msg.result))
    if n:
        values.append((now_us, n))


# --- the same flood on real processes ------------------------------------------------------------

class _ListFlood(threading.Thread):
    """PARAM_REQUEST_LIST from system FLOOD_SYSID at `rate_hz` until stopped."""

    def __init__(self, url: str, rate_hz: float) -> None:
        super().__init__(name="param-list-flood", daemon=True)
        from pymavlink import mavutil

        from firmware_py.mavlink.dialect import NAME as DIALECT

        self.conn = mavutil.mavlink_connection(url, source_system=FLOOD_SYSID, source_component=190,
                                               dialect=DIALECT)
        self.rate_hz = rate_hz
        self.stop = threading.Event()
        self.sent = 0
        self.answers = 0

    def run(self) -> None:
        t0 = time.monotonic()
        while not self.stop.is_set():
            with suppress(OSError):
                self.conn.mav.param_request_list_send(1, 1)
            self.sent += 1
            if self.sent % 15 == 0:
                while self.conn.recv_match(type="PARAM_VALUE", blocking=False) is not None:
                    self.answers += 1
                time.sleep(max(0.0, t0 + self.sent / self.rate_hz - time.monotonic()))
        self.conn.close()


def _hold_in_list_flood(link: Any, _beats: Any, url: str, rate_hz: float, seed: int, row: dict[str, Any],
                        problems: list[str]) -> None:
    """One run of `param_list_flood_hil` on the armed robot: the flood for 1-2 s, then the
    operator's SET_MODE Hold; what came back goes into `row`, what went wrong into `problems`."""
    flood = _ListFlood(url, rate_hz)
    flood.start()
    try:
        time.sleep(1.0 + random.Random(seed).random())
        stamp = None
        while (msg := link.conn.recv_match(blocking=False)) is not None:
            stamp = getattr(msg, "time_boot_ms", None) or stamp
        m = link.m
        t_send = time.monotonic()
        link.conn.mav.set_mode_send(link.sysid, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(Mode.HOLD))
        ack = link.recv("COMMAND_ACK", 1.0, cond=lambda a, c=m.MAV_CMD_DO_SET_MODE: a.command == c)
        row["ack_after_ms"] = None if ack is None else round((time.monotonic() - t_send) * 1000, 1)
        row["robot_ms_before_send"] = stamp
        if ack is None or ack.result != m.MAV_RESULT_ACCEPTED:
            problems.append(f"first SET_MODE Hold not ACKed within 1 s ({ack})")
        time.sleep(1.0)
    finally:
        flood.stop.set()
        flood.join(2)
        row.update(flood_sent=flood.sent, flood_answers=flood.answers)


@register("param_list_flood_hil", small=1, large=5, unit="runs",
          what="paced HIL, 1,500 PARAM_REQUEST_LIST/s from another system: the operator's first SET_MODE Hold "
               "ACKed and HOLD within 0.5 s of robot time")
def param_list_flood_hil(res: ScenarioResult, count: int, seed: int, progress: Any, rate_hz: float = 1500.0) -> None:
    from ground_station.lab.faults.floods import _as_operator, driving_robot

    runs = []
    for i in trials(count, progress):
        s = seed * 1000 + 4300 + i
        problems: list[str] = []
        row: dict[str, Any] = {"seed": s}
        with tempfile.TemporaryDirectory(prefix="qnav-listflood-") as tmp, \
                driving_robot(Path(tmp), s, 60.0) as ctx:
            _as_operator(ctx["robot"].url, problems, _hold_in_list_flood, ctx["robot"].url, rate_hz, s, row, problems)
        problems += ctx["problems"]
        st = ctx.get("stats")
        if st and row.get("robot_ms_before_send") is not None:
            t_ref = row["robot_ms_before_send"] * 1000
            hold = next((t for t in st.get("transitions", []) if t[0] >= t_ref and t[2] == "HOLD"), None)
            row["hold_after_robot_ms"] = None if hold is None else (hold[0] - t_ref) / 1000
            if hold is None:
                problems.append("no HOLD transition after the send")
            elif hold[0] - t_ref > 500_000:
                problems.append(f"HOLD {(hold[0] - t_ref) / 1000:.0f} ms of robot time after the send")
            faults = [t for t in st.get("transitions", []) if t[2] == "FAULT"]
            if faults:
                problems.append(f"FAULT at {faults[0][0]} us: {faults[0][3]}")
        elif not problems:
            problems.append("no robot stats or no robot stamp before the send")
        row["problems"] = problems
        runs.append(row)
        res.check(problems, f"run {i} seed {s}")
    res.figures["runs"] = runs
