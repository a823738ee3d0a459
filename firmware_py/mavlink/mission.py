"""Mission protocol engine (MAVLink mission microservice, robot side).

Owns the stored mission (the items exactly as uploaded, so a download returns what was sent) and the
transfer state machines: upload (a missing item re-requested every MIS_TIMEOUT_MS on the robot
clock, MIS_RETRIES times, then cancelled, the old mission kept), download, MISSION_CLEAR_ALL,
MISSION_SET_CURRENT and the "guided mode" item (current=2). Pure engine: `handle(msg, now_us)` and
`tick(now_us)` return replies.

Items: MAV_CMD_NAV_WAYPOINT only, in MAV_FRAME_LOCAL_NED or a global frame (converted around the
configured origin); waypoints go to the vehicle in world millimetres (x east, y north). Every item
(uploaded or a guided waypoint) is validated before anything is computed from it (`check_item`, on
`check_position`, which DO_REPOSITION and the position targets use too) and must lie on the robot's
map (`VehicleStatus.map_mm`). The rules and the MAV_MISSION_* answers: docs/mavlink.md, "Missions".
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from firmware_py.mavlink import frames as mav_frames
from firmware_py.mavlink.dialect import mavlink2
from firmware_py.mavlink.params import ParamStore
from firmware_py.vehicle import VehicleControl

M = mavlink2
MAX_ITEMS = 128
LOCAL_FRAMES = frozenset({M.MAV_FRAME_LOCAL_NED})
GLOBAL_FRAMES = frozenset({
    M.MAV_FRAME_GLOBAL, M.MAV_FRAME_GLOBAL_RELATIVE_ALT, M.MAV_FRAME_GLOBAL_INT,
    M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_FRAME_GLOBAL_TERRAIN_ALT,
    M.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
})
LOCAL_LIMIT_M = 200_000.0  # |x|, |y| of a local item: x * LOCAL_ITEM_SCALE stays inside int32
LAT_LIMIT_E7 = 900_000_000
LON_LIMIT_E7 = 1_800_000_000


@dataclass(frozen=True)
class Item:
    """A stored mission item in MISSION_ITEM_INT terms (x, y: 1e7 deg for
    global frames, metres * LOCAL_ITEM_SCALE for local)."""

    seq: int
    frame: int
    command: int
    autocontinue: int
    params: tuple[float, float, float, float]
    x: int
    y: int
    z: float


def check_position(local: bool, x: float, y: float) -> tuple[int, str] | None:
    """None if a position is finite and inside its frame's range (`local`: x north,
    y east in metres; global: latitude x, longitude y in degrees), else the
    MAV_MISSION_RESULT naming the field (INVALID_PARAM5_X / _PARAM6_Y) and the reason.
    The one range check for every position a GCS sends."""
    for which, value, code in (("x", x, M.MAV_MISSION_INVALID_PARAM5_X),
                               ("y", y, M.MAV_MISSION_INVALID_PARAM6_Y)):
        if not math.isfinite(value):
            return code, f"{which} is not a finite number"
        limit = LOCAL_LIMIT_M if local else (LAT_LIMIT_E7 if which == "x" else LON_LIMIT_E7) / 1e7
        if abs(value) > limit:
            return code, f"{which}={value:g} out of range (|{which}| <= {limit:g})"
    return None


def check_item(msg: mavlink2.MAVLink_message) -> tuple[int, str] | None:
    """(MAV_MISSION_RESULT, reason) if a MISSION_ITEM(_INT) cannot be stored, else None."""
    for i, p in enumerate((msg.param1, msg.param2, msg.param3, msg.param4)):
        if math.isinf(p):  # NaN means "unused" in MAVLink; an infinity means nothing
            return M.MAV_MISSION_INVALID_PARAM1 + i, f"mission item {msg.seq}: param{i + 1} is infinite"
    if not math.isfinite(msg.z):
        return M.MAV_MISSION_INVALID_PARAM7, f"mission item {msg.seq}: z is not a finite number"
    local = msg.frame in LOCAL_FRAMES
    x, y = msg.x, msg.y
    if msg.get_type() == "MISSION_ITEM_INT":  # scaled integers: back to metres / degrees
        scale = mav_frames.LOCAL_ITEM_SCALE if local else 1e7
        x, y = x / scale, y / scale
    error = check_position(local, x, y)
    if error is not None:
        return error[0], f"mission item {msg.seq}: {error[1]}"
    return None


def item_from_msg(msg: mavlink2.MAVLink_message) -> Item:
    """Normalise MISSION_ITEM (float) and MISSION_ITEM_INT to `Item`."""
    params = (msg.param1, msg.param2, msg.param3, msg.param4)
    if msg.get_type() == "MISSION_ITEM_INT":
        x, y = msg.x, msg.y
    else:  # float item: scale like MISSION_ITEM_INT, keeping the frame's meaning
        scale = mav_frames.LOCAL_ITEM_SCALE if msg.frame in LOCAL_FRAMES else 1e7
        x, y = round(msg.x * scale), round(msg.y * scale)
    return Item(msg.seq, msg.frame, msg.command, msg.autocontinue, params, x, y, msg.z)


def item_to_world(item: Item, origin_lat_e7: int, origin_lon_e7: int) -> tuple[int, int]:
    if item.frame in LOCAL_FRAMES:
        return mav_frames.ned_m_to_world(item.x / mav_frames.LOCAL_ITEM_SCALE, item.y / mav_frames.LOCAL_ITEM_SCALE)
    return mav_frames.global_to_world(item.x, item.y, origin_lat_e7, origin_lon_e7)


def map_bounds_error(map_mm: tuple[int, int] | None, x_mm: int, y_mm: int) -> tuple[int, str]:
    """Whether world point (x_mm, y_mm) lies on the robot's map (`VehicleStatus.map_mm`,
    None: no map known, nothing to check): (0, "") if so, else the MAV_MISSION_RESULT
    naming the MAVLink field that is off (x/param5 is north = world y, y/param6 is
    east = world x, in the local and the global frames alike) and the reason."""
    if map_mm is None:
        return 0, ""
    width, height = map_mm
    where = f"({x_mm / 1000:.2f}, {y_mm / 1000:.2f}) m"
    extent = f"the map's 0..{width / 1000:g} x 0..{height / 1000:g} m"
    if not 0 <= y_mm <= height:
        return int(M.MAV_MISSION_INVALID_PARAM5_X), f"{where} is north/south of {extent}"
    if not 0 <= x_mm <= width:
        return int(M.MAV_MISSION_INVALID_PARAM6_Y), f"{where} is east/west of {extent}"
    return 0, ""


class MissionEngine:
    """Robot side of the mission protocol."""

    def __init__(self, mav: mavlink2.MAVLink, vehicle: VehicleControl, params: ParamStore,
                 statustext: Callable[[str, int], list[mavlink2.MAVLink_message]]) -> None:
        self.mav = mav
        self.vehicle = vehicle
        self.params = params
        self._statustext = statustext  # (text, severity) -> list[msg]
        self.items: list[Item] = []
        self.on_mission_changed: Callable[[], None] | None = None  # after a new mission is stored
        # upload transfer
        self._up_partner: tuple[int, int] | None = None
        self._up_count = 0
        self._up_items: list[Item] = []
        self._up_deadline = 0
        self._up_retries = 0
        # download transfer
        self._down_partner: tuple[int, int] | None = None
        self._down_deadline = 0

    @property
    def uploading(self) -> bool:
        return self._up_partner is not None

    def _ack(self, partner: tuple[int, int], result: int) -> mavlink2.MAVLink_message:
        return self.mav.mission_ack_encode(partner[0], partner[1], result, M.MAV_MISSION_TYPE_MISSION)

    def _told(self, partner: tuple[int, int], result: int, text: str,
              severity: int = M.MAV_SEVERITY_WARNING) -> list[mavlink2.MAVLink_message]:
        """`text` as a STATUSTEXT, then the MISSION_ACK with `result`."""
        return self._statustext(text, severity) + [self._ack(partner, result)]

    def _timeout_us(self) -> int:
        return self.params.get("MIS_TIMEOUT_MS") * 1000

    def _request(self, seq: int) -> mavlink2.MAVLink_message:
        assert self._up_partner is not None
        tsys, tcomp = self._up_partner
        return self.mav.mission_request_int_encode(tsys, tcomp, seq, M.MAV_MISSION_TYPE_MISSION)

    # --- engine ------------------------------------------------------------------
    def handle(self, msg: mavlink2.MAVLink_message, now_us: int) -> list[mavlink2.MAVLink_message]:
        kind = msg.get_type()
        partner = (msg.get_srcSystem(), msg.get_srcComponent())
        mission_type = getattr(msg, "mission_type", M.MAV_MISSION_TYPE_MISSION)
        if kind in ("MISSION_COUNT", "MISSION_REQUEST_LIST", "MISSION_CLEAR_ALL") and \
                mission_type != M.MAV_MISSION_TYPE_MISSION:
            if kind == "MISSION_REQUEST_LIST":  # an empty fence/rally list, as ArduPilot-less GCSs expect
                return [self.mav.mission_count_encode(partner[0], partner[1], 0, mission_type)]
            return [self.mav.mission_ack_encode(partner[0], partner[1], M.MAV_MISSION_UNSUPPORTED, mission_type)]
        if kind == "MISSION_COUNT":
            return self._start_upload(msg, partner, now_us)
        if kind in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            return self._item(msg, partner, now_us)
        if kind == "MISSION_REQUEST_LIST":
            self._down_partner = partner
            self._down_deadline = now_us + self._timeout_us() * (self.params.get("MIS_RETRIES") + 1)
            return [self.mav.mission_count_encode(partner[0], partner[1], len(self.items),
                                                  M.MAV_MISSION_TYPE_MISSION)]
        if kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            return self._send_item(msg, partner, now_us, kind == "MISSION_REQUEST_INT")
        if kind == "MISSION_ACK":
            if self._down_partner == partner:
                self._down_partner = None
            return []
        if kind == "MISSION_CLEAR_ALL":
            if self.uploading:
                return self._told(partner, M.MAV_MISSION_DENIED, "mission clear refused: upload in progress")
            ok, reason = self.vehicle.set_mission([])
            if not ok:
                return self._told(partner, M.MAV_MISSION_DENIED, f"mission clear refused: {reason}")
            self.items = []
            self._changed()
            return [self._ack(partner, M.MAV_MISSION_ACCEPTED)]
        if kind == "MISSION_SET_CURRENT":
            return self.set_current(msg.seq)
        return []

    def set_current(self, seq: int) -> list[mavlink2.MAVLink_message]:
        """MISSION_SET_CURRENT: answered by MISSION_CURRENT (STATUSTEXT on refusal)."""
        out: list[mavlink2.MAVLink_message] = []
        if not 0 <= seq < len(self.items):
            out += self._statustext(f"mission set current refused: no item {seq}", M.MAV_SEVERITY_WARNING)
        else:
            ok, reason = self.vehicle.set_mission_current(seq)
            if not ok:
                out += self._statustext(f"mission set current refused: {reason}", M.MAV_SEVERITY_WARNING)
        st = self.vehicle.status()
        return out + [self.mav.mission_current_encode(st.mission_seq, st.mission_count, 0, 0)]

    def _start_upload(self, msg: mavlink2.MAVLink_message, partner: tuple[int, int], now_us: int) -> list[mavlink2.MAVLink_message]:
        if self.uploading and partner != self._up_partner:
            return [self._ack(partner, M.MAV_MISSION_DENIED)]
        count = msg.count
        if count > MAX_ITEMS:
            return self._told(partner, M.MAV_MISSION_NO_SPACE, f"mission of {count} items exceeds {MAX_ITEMS}")
        if count == 0:
            self._up_partner = None
            return self._commit([], partner)
        self._up_partner, self._up_count, self._up_items = partner, count, []
        self._up_retries = 0
        self._up_deadline = now_us + self._timeout_us()
        return [self._request(0)]

    def _item(self, msg: mavlink2.MAVLink_message, partner: tuple[int, int], now_us: int) -> list[mavlink2.MAVLink_message]:
        if getattr(msg, "current", 0) == 2 and not (self.uploading and partner == self._up_partner):
            return self._guided_item(msg, partner)
        if not self.uploading or partner != self._up_partner:
            return []  # stray item: nothing is being uploaded from this GCS
        expected = len(self._up_items)
        if msg.seq != expected:  # duplicate or out of order: ask again for the one we need
            return [self._request(expected)]
        error = check_item(msg)  # before item_from_msg: a NaN float x/y cannot be rounded
        if error is None:
            item = item_from_msg(msg)
            if item.command != M.MAV_CMD_NAV_WAYPOINT:
                error = (M.MAV_MISSION_UNSUPPORTED, f"mission item {item.seq}: command {item.command} unsupported "
                         "(NAV_WAYPOINT only)")
            elif item.frame not in LOCAL_FRAMES and item.frame not in GLOBAL_FRAMES:
                error = (M.MAV_MISSION_UNSUPPORTED_FRAME, f"mission item {item.seq}: frame {item.frame} unsupported")
            else:
                x_mm, y_mm = item_to_world(item, self.params.get("ORIGIN_LAT"), self.params.get("ORIGIN_LON"))
                code, why = map_bounds_error(self.vehicle.status().map_mm, x_mm, y_mm)
                if code:
                    error = (code, f"mission item {item.seq} refused: {why}")
        if error is not None:
            self._up_partner = None
            return self._told(partner, error[0], error[1])
        self._up_items.append(item)
        self._up_retries = 0
        self._up_deadline = now_us + self._timeout_us()
        if len(self._up_items) < self._up_count:
            return [self._request(len(self._up_items))]
        self._up_partner = None
        return self._commit(self._up_items, partner)

    def _guided_item(self, msg: mavlink2.MAVLink_message, partner: tuple[int, int]) -> list[mavlink2.MAVLink_message]:
        """A "guided mode" waypoint (MISSION_ITEM(_INT) with current=2, ArduPilot's
        go-to outside a mission upload): a goal, answered by MISSION_ACK. Checked
        like an uploaded item first (a NaN or huge x/y is refused with its code)."""
        error = check_item(msg)
        if error is not None:
            return self._told(partner, error[0], f"guided goal refused: {error[1]}")
        item = item_from_msg(msg)
        result, reason = int(M.MAV_MISSION_ACCEPTED), ""
        if item.command != M.MAV_CMD_NAV_WAYPOINT:
            result, reason = int(M.MAV_MISSION_UNSUPPORTED), f"command {item.command} unsupported"
        elif item.frame not in LOCAL_FRAMES and item.frame not in GLOBAL_FRAMES:
            result, reason = int(M.MAV_MISSION_UNSUPPORTED_FRAME), f"frame {item.frame} unsupported"
        else:
            x_mm, y_mm = item_to_world(item, self.params.get("ORIGIN_LAT"), self.params.get("ORIGIN_LON"))
            result, reason = map_bounds_error(self.vehicle.status().map_mm, x_mm, y_mm)
            if not result:
                ok, reason = self.vehicle.set_goal(x_mm, y_mm)
                result = int(M.MAV_MISSION_ACCEPTED if ok else M.MAV_MISSION_DENIED)
        out = self._statustext(f"guided goal refused: {reason}", M.MAV_SEVERITY_WARNING) if result else []
        return out + [self._ack(partner, result)]

    def _commit(self, items: list[Item], partner: tuple[int, int]) -> list[mavlink2.MAVLink_message]:
        lat0, lon0 = self.params.get("ORIGIN_LAT"), self.params.get("ORIGIN_LON")
        waypoints = [item_to_world(it, lat0, lon0) for it in items]
        ok, reason = self.vehicle.set_mission(waypoints)
        if not ok:
            return self._told(partner, M.MAV_MISSION_DENIED, f"mission refused: {reason}")
        self.items = list(items)
        self._changed()
        return self._told(partner, M.MAV_MISSION_ACCEPTED, f"mission of {len(items)} items stored",
                          M.MAV_SEVERITY_INFO)

    def _changed(self) -> None:
        if self.on_mission_changed is not None:
            self.on_mission_changed()

    def _send_item(self, msg: mavlink2.MAVLink_message, partner: tuple[int, int], now_us: int,
                   as_int: bool) -> list[mavlink2.MAVLink_message]:
        if not 0 <= msg.seq < len(self.items):
            return [self._ack(partner, M.MAV_MISSION_INVALID_SEQUENCE)]
        if self._down_partner == partner:
            self._down_deadline = now_us + self._timeout_us() * (self.params.get("MIS_RETRIES") + 1)
        it = self.items[msg.seq]
        current = 1 if msg.seq == self.vehicle.status().mission_seq else 0
        scale = mav_frames.LOCAL_ITEM_SCALE if it.frame in LOCAL_FRAMES else 1e7
        # MISSION_ITEM_INT carries the stored integers; MISSION_ITEM their float meaning
        encode, x, y = ((self.mav.mission_item_int_encode, it.x, it.y) if as_int
                        else (self.mav.mission_item_encode, it.x / scale, it.y / scale))
        return [encode(partner[0], partner[1], it.seq, it.frame, it.command, current, it.autocontinue,
                       *it.params, x, y, it.z, M.MAV_MISSION_TYPE_MISSION)]

    def tick(self, now_us: int) -> list[mavlink2.MAVLink_message]:
        out: list[mavlink2.MAVLink_message] = []
        if self.uploading and now_us >= self._up_deadline:
            if self._up_retries >= self.params.get("MIS_RETRIES"):
                partner = self._up_partner
                assert partner is not None  # uploading
                self._up_partner = None
                out += self._told(partner, M.MAV_MISSION_OPERATION_CANCELLED,
                                  "mission upload timed out; previous mission kept")
            else:
                self._up_retries += 1
                self._up_deadline = now_us + self._timeout_us()
                out.append(self._request(len(self._up_items)))
        if self._down_partner is not None and now_us >= self._down_deadline:
            self._down_partner = None
        return out
