"""The robot's MAVLink 2 node: core engine plus a thin transport shell.

`MavNode` (the core) owns the routing of every incoming message - signing filter, target check,
parameters, commands, missions, goals, SETUP_SIGNING, FTP - plus the GCS failsafe and the telemetry
schedule: `handle(msg, now_us)` and `tick(now_us)` return the messages to send, nothing else
happens; time is the robot clock's. `handle` never raises: a handler's exception is counted per
message kind (`handler_errors`), logged once per kind and answered with a STATUSTEXT.

`MavShell` is the I/O around it on any pymavlink connection string (`poll`, never blocking, or
`serve`, its own loop).

docs/mavlink.md has the rest: "Node structure" (the link thread, the UDP parser reset, the serial
send budget), "GCS failsafe" (`check_failsafe`, `failsafe_on_control`), "Who may steer: SYSID_MYGCS"
and "Signing" (SETUP_SIGNING over network and serial links, SIGN_NET_SETUP).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import time
from collections import Counter, deque
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

from firmware_py.mavlink import authority
from firmware_py.mavlink import frames as mav_frames
from firmware_py.mavlink.commands import CommandHandler
from firmware_py.mavlink.dialect import NAME as DIALECT
from firmware_py.mavlink.dialect import mavlink2
from firmware_py.mavlink.mission import MissionEngine, check_position, map_bounds_error
from firmware_py.mavlink.param_stream import RATE_HZ, SERIAL_RATE_HZ, ParamStream
from firmware_py.mavlink.params import MAV_PARAM_TYPE_INT32, ParamStore, as_float32
from firmware_py.mavlink.signing import Signing
from firmware_py.mavlink.telemetry import (
    AUTOPILOTS,
    DEFAULT_AUTOPILOT,
    STREAMS,
    NodeStats,
    Telemetry,
)
from firmware_py.mavlink.tx_budget import TxBudget, frame_len
from firmware_py.vehicle import VehicleControl

log = logging.getLogger("qnav.mavlink")
M = mavlink2
DEFAULT_URL = "udpout:127.0.0.1:14550"
MISSION_MSGS = frozenset({
    "MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ITEM", "MISSION_REQUEST_LIST", "MISSION_REQUEST_INT",
    "MISSION_REQUEST", "MISSION_ACK", "MISSION_CLEAR_ALL", "MISSION_SET_CURRENT",
})
SIGNED_ONLY = frozenset({"SETUP_SIGNING", "FILE_TRANSFER_PROTOCOL"})
FTP_PAYLOAD_LEN = 251
POSITION_MASK_XY = 0b11  # type_mask bits "ignore x" / "ignore y"
# SET_POSITION_TARGET_LOCAL_NED frames: absolute, or offsets from the robot (north/east, or forward/right)
LOCAL_TARGET_FRAMES = frozenset({M.MAV_FRAME_LOCAL_NED, M.MAV_FRAME_LOCAL_OFFSET_NED, M.MAV_FRAME_BODY_NED,
                                 M.MAV_FRAME_BODY_OFFSET_NED})
NETWORK_PREFIXES = ("udp", "tcp", "ws")  # pymavlink connection strings that are not a local serial line


def is_network_url(url: str) -> bool:
    """True unless `url` is a serial device (the robot's physical link)."""
    return url.lower().startswith(NETWORK_PREFIXES) or ":" in url.split("/")[0]


RC_TRIM_US, RC_SPAN_US = 1500, 400  # ArduPilot Rover's RC defaults: 1100..1900 us, 1500 neutral


def sticks_of_rc(steering_us: int, throttle_us: int) -> tuple[int, int] | None:
    """(x, r) MANUAL_CONTROL sticks from RC_CHANNELS_OVERRIDE channel 1 (steering, right = clockwise)
    and channel 3 (throttle), as ArduPilot Rover maps them; None when both are released (0) or
    ignored (UINT16_MAX): then it is no sample, and the deadman stops the wheels."""
    def axis(us: int) -> int | None:
        if us in (0, 0xFFFF):
            return None
        return max(-1000, min(1000, (int(us) - RC_TRIM_US) * 1000 // RC_SPAN_US))
    r, x = axis(steering_us), axis(throttle_us)
    if r is None and x is None:
        return None
    return x or 0, r or 0


def robot_uid(storage_dir: Path | None) -> tuple[int, str]:
    """The robot's 64-bit id for AUTOPILOT_VERSION.uid, made once (random) and kept in its storage
    (firmware_py.storage.UID_FILE), so a ground station tells two robots apart across reboots; (0,
    "") without storage, (0, why) when it cannot be read or made."""
    if storage_dir is None:
        return 0, ""
    from firmware_py.atomic import atomic_write
    from firmware_py.storage import UID_FILE

    path = storage_dir / UID_FILE.lstrip("/")
    try:
        if path.is_file():
            text = path.read_text().strip()
            if len(text) == 16:
                return int(text, 16), ""
        uid = int.from_bytes(os.urandom(8), "little") or 1
        atomic_write(path, f"{uid:016x}\n", make_parents=True)
        return uid, ""
    except (OSError, ValueError) as exc:
        return 0, f"robot uid not available: {exc}"


class FtpService(Protocol):
    """What `MavNode` needs of its FTP server (`ftp_server.FtpServer` is one)."""

    def handle(self, payload: bytes | bytearray, now_us: int, owner: tuple[int, int] = (0, 0)) -> list[bytes]: ...
    def expire(self, now_us: int) -> None: ...
    def poll(self, now_us: int) -> list[tuple[tuple[int, int], bytes]]: ...
    def drain_texts(self) -> list[tuple[int, str]]: ...


class MavNode:
    """MAVLink node core: a pure state machine over pymavlink message objects.

    `ftp` (an `FtpService`) replies go back in FILE_TRANSFER_PROTOCOL frames to
    the requester, its texts as STATUSTEXT. `reboot_hook` reloads the policy from
    storage on a PREFLIGHT_REBOOT_SHUTDOWN (after the node reloaded its params).
    """

    def __init__(self, vehicle: VehicleControl, params: ParamStore, signing: Signing | None = None, *,
                 reboot_hook: Callable[[], tuple[bool, str]] | None = None,
                 ftp: FtpService | None = None, network_link: bool = True) -> None:
        self.vehicle = vehicle
        self.network_link = network_link  # SETUP_SIGNING without a key needs SIGN_NET_SETUP then
        self.params = params
        self.signing = signing if signing is not None else Signing(None)
        self.reboot_hook = reboot_hook
        self.ftp = ftp
        self.sysid = params.get("SYSID_THISMAV")
        self.compid = params.get("MAV_COMPID")
        self.mav = mavlink2.MAVLink(None, self.sysid, self.compid)  # message factory only
        self.stats = NodeStats()
        self.telemetry = Telemetry(self.mav, params)
        self.mission = MissionEngine(self.mav, vehicle, params, self.telemetry.statustext)
        self.mission.on_mission_changed = self.telemetry.mission_changed
        self.commands = CommandHandler(self.mav, vehicle, self.telemetry, self.mission, self._reboot)
        self.gcs_last_heartbeat_us: int | None = None
        self.gcs_sysid: int | None = None  # the GCS that keeps the failsafe alive (SYSID_MYGCS)
        self.foreign_gcs_heartbeats = 0
        self._gcs_seen: set[int] = set()  # GCS system ids heard (bounded): a new one is sent the origin at once
        self.gate = authority.ControlGate()  # who may steer (SYSID_MYGCS)
        # PARAM_REQUEST_LIST answers, sent in the background at a rate the link carries
        self.param_stream = ParamStream(RATE_HZ if network_link else SERIAL_RATE_HZ)
        self.handler_errors: dict[str, int] = {}  # message kind -> unexpected exceptions
        self.refused_setup_signing = 0
        self.failsafe = False
        self.failsafe_since_us: int | None = None  # robot time the failsafe last tripped
        self.failsafe_on_control = False  # True: the control loop calls check_failsafe (module doc)
        self._control_texts: deque[tuple[str, int]] = deque(maxlen=64)  # control thread -> link thread
        self.reboots = 0
        self._pending: list[mavlink2.MAVLink_message] = []
        self._now_us = 0

    # --- boot ---------------------------------------------------------------------
    def boot(self, now_us: int, key_file: str | os.PathLike[str] | None = None,
             overrides: dict[str, int] | None = None) -> None:
        """Load params and signing state from storage, set `overrides` (the command line's settings,
        which win for this run and are stored), then configure the vehicle once. Warnings (corrupt
        files, an override out of range) are sent as STATUSTEXT on the first tick."""
        warnings = self.params.load() + self.signing.load(now_us, key_file)
        for name, value in (overrides or {}).items():
            ok, why = self.params.set(name, value)
            if not ok:
                warnings.append(f"command line value not representable as a parameter: {why}")
        self._apply_params(reboot=True)
        storage_dir = self.params.path.parent.parent if self.params.path is not None else None
        uid, why = robot_uid(storage_dir)
        self.telemetry.uid = uid
        if why:
            warnings.append(why)
        if storage_dir is not None and self.ftp is not None:  # component metadata, served over FTP
            from firmware_py.mavlink.metadata import write_metadata
            from firmware_py.mavlink.telemetry import FLIGHT_SW_VERSION

            self.telemetry.metadata_crc, why = write_metadata(storage_dir, FLIGHT_SW_VERSION)
            if why:
                warnings.append(why)
        self._pending += [m for w in warnings for m in self._warn(w)]

    def _apply_params(self, reboot: bool) -> None:
        self.vehicle.apply_config(self.params.vehicle_config())
        self.signing.require = bool(self.params.get("SIGN_REQUIRE"))
        if reboot:
            self.sysid = self.params.get("SYSID_THISMAV")
            self.compid = self.params.get("MAV_COMPID")
            self.mav.srcSystem, self.mav.srcComponent = self.sysid, self.compid
            self.telemetry.reset_intervals()

    def _reboot(self) -> list[mavlink2.MAVLink_message]:
        self.reboots += 1
        out = [m for w in self.params.load() for m in self._warn(w)]
        self._apply_params(reboot=True)
        self.signing.persist(self._now_us)
        if self.reboot_hook is not None:
            ok, reason = self.reboot_hook()
            if not ok:
                out += self.telemetry.statustext(f"reboot: policy reload failed: {reason}", M.MAV_SEVERITY_ERROR)
        out += self.telemetry.statustext("reboot complete", M.MAV_SEVERITY_INFO)
        return out

    # --- input ----------------------------------------------------------------------
    def handle(self, msg: mavlink2.MAVLink_message, now_us: int) -> list[mavlink2.MAVLink_message]:
        """Route one message; never raises (see the module doc)."""
        try:
            return self._handle(msg, now_us)
        except Exception as exc:  # the last line of per-message isolation: count, log once, go on
            try:
                kind = str(msg.get_type())
            except Exception:
                kind = type(msg).__name__
            n = self.handler_errors.get(kind, 0) + 1
            self.handler_errors[kind] = n
            self.stats.rx_dropped += 1
            if n == 1:
                log.exception("handler for %s failed (counted; logged once per kind)", kind)
            return self.telemetry.statustext(f"{kind} refused: {type(exc).__name__}", M.MAV_SEVERITY_ERROR)

    def _handle(self, msg: mavlink2.MAVLink_message, now_us: int) -> list[mavlink2.MAVLink_message]:
        self._now_us = now_us
        self.stats.rx_total += 1
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.stats.rx_dropped += 1
            return []
        if self.signing.key is not None:
            self.signing.current_timestamp(now_us)  # the window ahead is measured from now
        if not self.signing.accept(msg):
            self.stats.rx_dropped += 1
            self.stats.signing_dropped = self.signing.dropped
            return []
        if (msg.get_srcSystem(), msg.get_srcComponent()) == (self.sysid, self.compid):
            return []  # our own frame looped back
        target = authority.target_of(msg)  # MANUAL_CONTROL names it `target`
        if target not in (None, 0, self.sysid):
            return []
        target_comp = getattr(msg, "target_component", None)
        if target_comp not in (None, 0, self.compid):
            return []
        if kind == "HEARTBEAT":
            return self._heartbeat(msg, now_us)
        refused = self.gate.refuse(msg, kind, self.params.get("SYSID_MYGCS"), now_us)
        if refused is not None:
            return self._refuse_control(msg, kind, refused)
        if kind.startswith("PARAM_"):
            return self._param(msg)
        if kind in ("COMMAND_LONG", "COMMAND_INT", "SET_MODE"):
            replies = self.commands.handle(msg, now_us, self.stats)
            if (self.gcs_last_heartbeat_us is not None and not self.failsafe
                    and msg.get_srcSystem() == self._failsafe_gcs()
                    and any(r.get_type() == "COMMAND_ACK" and r.result == M.MAV_RESULT_ACCEPTED for r in replies)):
                # a command the failsafe's GCS got accepted proves it alive as its heartbeat would
                # (ArduPilot counts MANUAL_CONTROL so): `qnav arm`, `qnav mode auto` typed between two
                # monitors keep the watch; they never start it, nor clear a failsafe
                self.gcs_last_heartbeat_us = now_us
            return replies
        if kind in MISSION_MSGS:
            return self.mission.handle(msg, now_us)
        if kind in ("SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT"):
            return self._goal(msg, now_us)
        if kind == "MANUAL_CONTROL":  # sticks for Manual mode (control/manual.py); no reply, as ArduPilot
            self.vehicle.manual_control(int(msg.x), int(msg.r), now_us)
            return []
        if kind == "RC_CHANNELS_OVERRIDE":  # MAVProxy's `rc` and joystick module, as for ArduPilot Rover
            sticks = sticks_of_rc(msg.chan1_raw, msg.chan3_raw)
            if sticks is not None:
                self.vehicle.manual_control(*sticks, now_us)
            return []
        if self.signing.key is not None and not self.signing.last_signed and kind in SIGNED_ONLY:
            # SIGN_REQUIRE=0 relaxes commands, never key changes or file access
            self.signing.dropped_unsigned += 1
            self.stats.rx_dropped += 1
            return []
        if kind == "SETUP_SIGNING":
            if (self.signing.key is None and self.network_link and not self.params.get("SIGN_NET_SETUP")):
                self.refused_setup_signing += 1
                return self._warn("unsigned SETUP_SIGNING refused: SIGN_NET_SETUP=0")
            key = bytes(msg.secret_key)
            if len(key) != 32:
                return self._warn("SETUP_SIGNING refused: key is not 32 bytes")
            text = self.signing.setup(key, int(msg.initial_timestamp))
            return self.telemetry.statustext(text, M.MAV_SEVERITY_NOTICE)
        if kind == "FILE_TRANSFER_PROTOCOL" and self.ftp is not None:
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            replies = self.ftp.handle(bytes(msg.payload), now_us, src)
            return [self.mav.file_transfer_protocol_encode(0, src[0], src[1], list(p.ljust(FTP_PAYLOAD_LEN, b"\0")))
                    for p in replies] + self._ftp_texts()
        return []

    def _warn(self, text: str) -> list[mavlink2.MAVLink_message]:
        return self.telemetry.statustext(text, M.MAV_SEVERITY_WARNING)

    def _refuse_control(self, msg: mavlink2.MAVLink_message, kind: str, why: str) -> list[mavlink2.MAVLink_message]:
        """A control input from a system that may not steer (authority.py): dropped and counted; a
        command addressed to us is answered DENIED so that its sender stops retrying."""
        self.stats.rx_dropped += 1
        if authority.target_of(msg) == 0:
            return []  # a broadcast: no answer (a flood of them must not make one each)
        if kind in authority.COMMAND_MSGS or kind == "SET_MODE":
            command = M.MAV_CMD_DO_SET_MODE if kind == "SET_MODE" else int(msg.command)
            return [self.mav.command_ack_encode(command, M.MAV_RESULT_DENIED, 0, 0, msg.get_srcSystem(),
                                                msg.get_srcComponent())]
        return []

    def _tick_refusals(self, now_us: int) -> list[mavlink2.MAVLink_message]:
        text = self.gate.summary(now_us, self.params.get("SYSID_MYGCS"))
        if text is None:
            return []
        log.warning("%s", text)
        return self._warn(text)

    def _ftp_texts(self) -> list[mavlink2.MAVLink_message]:
        if self.ftp is None:
            return []
        return [m for severity, text in self.ftp.drain_texts() for m in self.telemetry.statustext(text, severity)]

    def _failsafe_gcs(self) -> int | None:
        """The system id whose heartbeats keep the GCS failsafe alive: SYSID_MYGCS, or with 0 the
        first GCS heard after boot (None until then)."""
        return self.params.get("SYSID_MYGCS") or self.gcs_sysid

    def _heartbeat(self, msg: mavlink2.MAVLink_message, now_us: int) -> list[mavlink2.MAVLink_message]:
        if msg.type != M.MAV_TYPE_GCS:
            return []
        src = msg.get_srcSystem()
        if src not in self._gcs_seen and len(self._gcs_seen) < 16:
            self._gcs_seen.add(src)  # a ground station joins: it gets home and origin at once
            self.telemetry.announce_origin()
        mine = self._failsafe_gcs()
        if mine is None:
            self.gcs_sysid = mine = src  # SYSID_MYGCS=0: the first GCS seen after boot
            log.info("GCS failsafe follows system id %d (first GCS heartbeat)", src)
        if src != mine:
            self.foreign_gcs_heartbeats += 1  # another GCS (or a spoofer) keeps nothing alive
            return []
        self.gcs_last_heartbeat_us = now_us
        if self.failsafe:
            self.failsafe = False
            self.vehicle.set_failsafe(False)
            return self.telemetry.statustext("GCS failsafe cleared", M.MAV_SEVERITY_NOTICE)
        return []

    # --- parameters ---------------------------------------------------------------------
    def param_value(self, name: str) -> mavlink2.MAVLink_message:
        value = self.params.get(name)
        return self.mav.param_value_encode(name.encode(), as_float32(value), MAV_PARAM_TYPE_INT32,
                                           len(self.params), self.params.index(name))

    def _param(self, msg: mavlink2.MAVLink_message) -> list[mavlink2.MAVLink_message]:
        kind = msg.get_type()
        self._refresh_readonly()
        if kind == "PARAM_REQUEST_LIST":  # streamed (param_stream.py): a request costs no burst of answers
            self.param_stream.request((msg.get_srcSystem(), msg.get_srcComponent()))
            return self._param_stream_due(self._now_us)
        if kind == "PARAM_REQUEST_READ":
            if msg.param_index >= 0:
                names = self.params.names()
                if msg.param_index < len(names):
                    return [self.param_value(names[msg.param_index])]
                return self._warn(f"no parameter index {msg.param_index}")
            if msg.param_id in self.params:
                return [self.param_value(msg.param_id)]
            return self._warn(self.params.unknown(msg.param_id))
        if kind == "PARAM_SET":
            name = msg.param_id
            ok, reason = self.params.set(name, msg.param_value, check=self.vehicle.check_config, remote=True)
            if name not in self.params:
                return self._warn(reason)
            out = [] if ok else self._warn(f"param set refused: {reason}")
            if ok:
                failed = self.params.pop_save_failure()  # a save in this thread (no storage worker)
                if failed:
                    out += self.telemetry.statustext(failed, M.MAV_SEVERITY_ERROR)
                d = self.params.definition(name)
                if d.reboot_required:
                    out += self.telemetry.statustext(f"{name} takes effect after reboot", M.MAV_SEVERITY_NOTICE)
                else:
                    self._apply_params(reboot=False)
            return out + [self.param_value(name)]
        return []

    def _param_stream_due(self, now_us: int) -> list[mavlink2.MAVLink_message]:
        names = self.params.names()
        return [self.param_value(names[index]) for _, index in self.param_stream.due(now_us, len(names))]

    def _refresh_readonly(self) -> None:
        st = self.vehicle.status()
        self.params.update_policy(st.policy_id, st.policy_crc)

    # --- goals ----------------------------------------------------------------------------
    def _goal(self, msg: mavlink2.MAVLink_message, now_us: int) -> list[mavlink2.MAVLink_message]:
        if msg.type_mask & POSITION_MASK_XY:
            return self._warn("goal refused: position ignored in type_mask")
        if msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
            if msg.coordinate_frame not in LOCAL_TARGET_FRAMES:
                return self._warn(f"goal refused: frame {msg.coordinate_frame} unsupported "
                                  "(LOCAL_NED, LOCAL_OFFSET_NED, BODY_NED, BODY_OFFSET_NED)")
            if not (math.isfinite(msg.x) and math.isfinite(msg.y)):  # round(NaN) would raise
                return self._warn("goal refused: position is not a finite number")
            bad = check_position(True, msg.x, msg.y)  # offsets too: metres from the robot
            if bad is not None:
                return self._warn(f"goal refused: {bad[1]}")
            if msg.coordinate_frame == M.MAV_FRAME_LOCAL_NED:
                x_mm, y_mm = mav_frames.ned_m_to_world(msg.x, msg.y)
            else:  # relative to where the robot is now (its believed pose), as ArduPilot Rover reads them
                st = self.vehicle.status()
                x_mm, y_mm = mav_frames.offset_to_world(st.x_mm, st.y_mm, st.heading_mrad,
                                                        msg.coordinate_frame != M.MAV_FRAME_LOCAL_OFFSET_NED,
                                                        msg.x, msg.y)
        else:
            if check_position(False, msg.lat_int / 1e7, msg.lon_int / 1e7) is not None:
                return self._warn("goal refused: latitude/longitude out of range")
            x_mm, y_mm = mav_frames.global_to_world(msg.lat_int, msg.lon_int, self.params.get("ORIGIN_LAT"),
                                                    self.params.get("ORIGIN_LON"))
        _, off_map = map_bounds_error(self.vehicle.status().map_mm, x_mm, y_mm)
        ok, reason = (False, off_map) if off_map else self.vehicle.set_goal(x_mm, y_mm)
        if not ok:
            return self._warn(f"goal refused: {reason}")
        return [self.telemetry.position_target((now_us // 1000) & 0xFFFFFFFF, x_mm, y_mm)]

    # --- time -------------------------------------------------------------------------------
    def tick(self, now_us: int) -> list[mavlink2.MAVLink_message]:
        """Failsafe check, vehicle events, mission timeouts, due telemetry."""
        self._now_us = now_us
        out, self._pending = self._pending, []
        if not self.failsafe_on_control:
            self.check_failsafe(now_us)  # first, and outside the guarded parts below
        while self._control_texts:
            text, severity = self._control_texts.popleft()
            out += self.telemetry.statustext(text, severity)
        for part in (self._tick_events, self.mission.tick, self._tick_ftp, self._tick_signing,
                     self._tick_params, self._tick_refusals, self._tick_telemetry):
            try:
                out += part(now_us)
            except Exception:  # one broken part must not starve the others (or the failsafe)
                kind = f"tick:{getattr(part, '__name__', 'part')}"
                n = self.handler_errors.get(kind, 0) + 1
                self.handler_errors[kind] = n
                if n == 1:
                    log.exception("%s failed (counted; logged once)", kind)
        return out

    def _tick_params(self, now_us: int) -> list[mavlink2.MAVLink_message]:
        """A parameter save that failed on the storage worker: the GCS was sent
        the new value already, so it is told the value will not survive a reboot."""
        failed = self.params.pop_save_failure()
        out = self.telemetry.statustext(failed, M.MAV_SEVERITY_ERROR) if failed else []
        if self.param_stream.active:
            self._refresh_readonly()
            out += self._param_stream_due(now_us)
        return out

    def _tick_events(self, now_us: int) -> list[mavlink2.MAVLink_message]:
        return [m for ev in self.vehicle.drain_events() for m in self.telemetry.event(ev)]

    def _tick_ftp(self, now_us: int) -> list[mavlink2.MAVLink_message]:
        if self.ftp is None:
            return []
        self.ftp.expire(now_us)
        done = [self.mav.file_transfer_protocol_encode(0, owner[0], owner[1], list(p.ljust(FTP_PAYLOAD_LEN, b"\0")))
                for owner, p in self.ftp.poll(now_us)]  # an activation finished off the link thread
        return done + self._ftp_texts()

    def _tick_signing(self, now_us: int) -> list[mavlink2.MAVLink_message]:
        self.signing.tick(now_us)
        self.stats.signing_dropped = self.signing.dropped
        return []

    def _tick_telemetry(self, now_us: int) -> list[mavlink2.MAVLink_message]:
        return self.telemetry.due(now_us, self.vehicle.status(), self.stats)

    def check_failsafe(self, now_us: int) -> None:
        """Trip the GCS failsafe when the last GCS heartbeat is older than
        FS_GCS_TOUT_MS; reads only ints and params, so the control loop can
        call it every tick. Its STATUSTEXTs go out with the next `tick`."""
        enabled = bool(self.params.get("FS_GCS_ENABLE"))
        if self.failsafe and not enabled:
            self.failsafe = False
            self.vehicle.set_failsafe(False)
            self._control_texts.append(("GCS failsafe cleared (disabled)", M.MAV_SEVERITY_NOTICE))
            return
        last = self.gcs_last_heartbeat_us
        if self.failsafe or not enabled or last is None:
            return
        timeout_ms = self.params.get("FS_GCS_TOUT_MS")
        if now_us - last <= timeout_ms * 1000:
            return
        self.failsafe = True
        self.failsafe_since_us = now_us
        self.vehicle.set_failsafe(True)
        if self.gcs_last_heartbeat_us != last and self.failsafe:
            # a heartbeat landed (link thread) between the check and the trip: undo, no text
            self.failsafe = False
            self.vehicle.set_failsafe(False)
            return
        action = ("none", "Hold", "disarm")[self.params.get("FS_GCS_ACTION")]
        self._control_texts.append((f"GCS failsafe: no GCS heartbeat for {timeout_ms} ms, {action}",
                                    M.MAV_SEVERITY_CRITICAL))


class MavShell:
    """Moves frames between a pymavlink connection and a `MavNode`."""

    def __init__(self, node: MavNode, url: str = DEFAULT_URL, *, baud: int = 57600) -> None:
        # MAVLink 2 from the first frame: pymavlink's v1 -> v2 switch would
        # replace the codec and lose the signing setup.
        os.environ["MAVLINK20"] = "1"
        from pymavlink import mavutil

        self.node = node
        self.conn = mavutil.mavlink_connection(url, baud=baud, dialect=DIALECT, source_system=node.sysid,
                                               source_component=node.compid, autoreconnect=True)
        self._key_version = -1
        self._datagrams = isinstance(self.conn, mavutil.mavudp)
        self.partial_dropped = 0  # UDP datagrams that ended inside a frame (see poll)
        self.budget_exhausted = 0  # polls that stopped on their time budget with input left
        self.handler_errors: dict[str, int] = {}  # message type (or parser/tick) -> exceptions caught
        self._cpu = (time.process_time(), time.monotonic())
        # a serial line carries baud/10 bytes a wall second: telemetry streams thin out to fit (tx_budget.py)
        self.tx_budget = None if is_network_url(url) else TxBudget.for_baud(baud)

    def _sync_signing(self, now_us: int) -> None:
        sig, s = self.node.signing, self.conn.mav.signing
        if self._key_version != sig.key_version:
            self._key_version = sig.key_version
            s.secret_key = sig.key
            s.sign_outgoing = sig.key is not None
            # accept everything at the parser: the node's Signing decides and counts
            s.allow_unsigned_callback = (lambda mav, msg_id: True) if sig.key is not None else None
            s.link_id = 0
        if sig.key is not None:
            # pymavlink's parser moves its timestamp up to any validly signed input
            # (2^48 wrap): the robot's own Signing decides what we send with.
            s.timestamp = sig.current_timestamp(now_us)
            s.stream_timestamps.clear()  # the node's Signing keeps the streams (bounded)

    def send(self, msgs: list[mavlink2.MAVLink_message], now_us: int) -> None:
        if not msgs:
            return
        self._sync_signing(now_us)
        mav = self.conn.mav
        mav.srcSystem, mav.srcComponent = self.node.sysid, self.node.compid
        budget, signed = self.tx_budget, self.node.signing.key is not None
        for m in msgs:
            if budget is not None and not budget.allow(
                    frame_len(m, signed), m.get_msgId() in STREAMS and m.get_msgId() != M.MAVLINK_MSG_ID_HEARTBEAT):
                continue  # this period's share of the radio is spent: the stream sends again next time it is due
            # an OSError: no peer yet (udpin before the first frame) or link down; telemetry is periodic
            with contextlib.suppress(OSError):
                mav.send(m)
        if self.node.signing.key is not None:
            self.node.signing.note_sent(mav.signing.timestamp)

    def poll(self, now_us: int, budget_s: float = 0.02, max_msgs: int = 200,
             yield_every_s: float = 0.0, yield_s: float = 0.0002) -> int:
        """Handle what has arrived (at most `max_msgs` frames or `budget_s` of wall
        time; the rest waits in the socket buffer), then tick. Never blocks, never
        raises for a frame. Returns the number of frames handled.

        `yield_every_s` > 0: after that much work, sleep `yield_s`, freeing the
        interpreter lock for the ticking thread (avoids the GIL convoy effect)."""
        self._sync_signing(now_us)
        t_end = time.perf_counter() + budget_s
        t_yield = time.perf_counter() + yield_every_s
        n = 0
        while n < max_msgs:
            if yield_every_s > 0 and time.perf_counter() >= t_yield:
                time.sleep(yield_s)
                t_yield = time.perf_counter() + yield_every_s
            try:
                msg = self.conn.recv_msg()
            except OSError:
                break
            except Exception as exc:  # the parser itself: count, never stop the poll
                self._handler_error("parser", exc)
                continue
            if msg is None:
                if not (self._datagrams and self.conn.mav.buf_len() > 0):
                    break  # nothing more has arrived
                # UDP: a datagram that ended inside a frame. Each sender's frames come whole in
                # their own datagrams, so the rest is garbage; kept, it would swallow the start of
                # the next datagram (another client's heartbeat): drop it and read on.
                self._drop_partial()
                n += 1
                continue
            n += 1
            try:
                replies = self.node.handle(msg, now_us)
            except Exception as exc:  # one bad frame costs one frame, not the poll (and never the tick)
                self._handler_error(msg.get_type(), exc)
                replies = []
            self.send(replies, now_us)
            if time.perf_counter() >= t_end:
                self.budget_exhausted += 1
                break
        cpu, wall = time.process_time(), time.monotonic()
        if wall - self._cpu[1] >= 1.0:
            self.node.stats.load_permille = int(1000 * (cpu - self._cpu[0]) / (wall - self._cpu[1]))
            self._cpu = (cpu, wall)
        try:
            out = self.node.tick(now_us)
        except Exception as exc:
            self._handler_error("tick", exc)
            out = []
        self.send(out, now_us)
        return n

    def _drop_partial(self) -> None:
        mav = self.conn.mav
        self.partial_dropped += 1
        self.node.stats.rx_dropped += 1
        mav.buf = bytearray()
        mav.buf_index = 0
        mav.expected_length = mavlink2.HEADER_LEN_V1 + 2

    def all_handler_errors(self) -> dict[str, int]:
        """Exceptions caught per kind, by the node's own per-message catch and
        by this shell's (parser, socket, anything the node let through)."""
        return dict(Counter(self.node.handler_errors) + Counter(self.handler_errors))

    def _handler_error(self, kind: str, exc: BaseException) -> None:
        """Count an exception out of a handler; log the first one of each kind."""
        self.handler_errors[kind] = self.handler_errors.get(kind, 0) + 1
        if self.handler_errors[kind] == 1:
            log.error("MAVLink %s handler raised %s: %s (dropped; further %s errors only counted)",
                      kind, type(exc).__name__, exc, kind)

    def close(self) -> None:
        self.node.signing.persist()
        self.conn.close()


def add_mavlink_args(parser: argparse.ArgumentParser) -> None:
    """`--mavlink URL` and `--signing-key FILE` for the robot's command line."""
    parser.add_argument("--mavlink", metavar="URL", default=DEFAULT_URL,
                        help=f"pymavlink connection string (default {DEFAULT_URL}; also udpin:, tcp:, "
                             "tcpin:, a serial device; 'none': no MAVLink)")
    parser.add_argument("--mavlink-baud", type=int, default=57600, help="baud rate for a serial device")
    parser.add_argument("--signing-key", metavar="FILE", default=None,
                        help="MAVLink 2 signing key file (32 bytes, 64 hex chars or a passphrase)")
    parser.add_argument("--mavlink-autopilot", choices=sorted(AUTOPILOTS), default=DEFAULT_AUTOPILOT,
                        help="autopilot type in the HEARTBEAT (default %(default)s): 'ardupilot' for MAVSDK, "
                             "which reads int parameters and names modes only for ArduPilot (docs/mavlink.md)")


def open_node(vehicle: VehicleControl, storage_dir: str | os.PathLike[str] | None, url: str, now_us: int, *,
              signing_key: str | None = None, baud: int = 57600,
              reboot_hook: Callable[[], tuple[bool, str]] | None = None, ftp: bool = True,
              overrides: dict[str, int] | None = None, autopilot: str = DEFAULT_AUTOPILOT) -> MavShell:
    """Build, boot and connect the node: params and signing state from
    `storage_dir` (then `overrides`, see MavNode.boot), and (with `ftp`) an
    FTP server on it whose policy activation is the vehicle's `activate_policy`."""
    server = None
    if ftp and storage_dir is not None:
        from firmware_py.background import Background
        from firmware_py.mavlink.ftp_server import FtpServer
        from firmware_py.storage import Storage

        # whole-file work (CRC32, the commit's fsyncs) on a worker: the link thread keeps beating
        server = FtpServer(Storage(storage_dir), activate=getattr(vehicle, "begin_activation", vehicle.activate_policy),
                           activate_map=getattr(vehicle, "begin_map_activation", None), offload=Background())
    node = MavNode(vehicle, ParamStore(storage_dir), Signing(storage_dir), reboot_hook=reboot_hook, ftp=server,
                   network_link=is_network_url(url))
    node.boot(now_us, signing_key, overrides)
    node.telemetry.autopilot = int(AUTOPILOTS[autopilot])
    return MavShell(node, url, baud=baud)
