"""The robot's geodetic origin on MAVLink (issue 46 item 7): GPS_GLOBAL_ORIGIN and
HOME_POSITION go out as soon as a ground station appears and whenever the origin
changes, not only every 5 s; a local mission position sent as lat/lon around the
origin comes back to the same world point within 1 cm (what `qnav mission upload`
relies on to put its waypoints on every GCS's map)."""

from __future__ import annotations

import math

import pytest

from firmware_py.mavlink import frames
from firmware_py.mavlink.dialect import mavlink2 as m
from firmware_py.mavlink.params import ParamStore
from firmware_py.mavlink.telemetry import NodeStats, Telemetry
from firmware_py.vehicle import VehicleStatus

ORIGIN = {m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, m.MAVLINK_MSG_ID_HOME_POSITION}
CMAC = (-353632610, 1491652300, 584000)  # ArduPilot SITL's default home


def _origin_msgs(out: list) -> list:
    return [msg for msg in out if msg.id in ORIGIN]


def test_origin_and_home_go_out_when_a_gcs_appears_and_when_the_origin_changes():
    params = ParamStore()
    for name, value in zip(("ORIGIN_LAT", "ORIGIN_LON", "ORIGIN_ALT_MM"), CMAC, strict=True):
        assert params.set(name, value)[0]
    tel = Telemetry(m.MAVLink(None, 1, 1), params)
    st, stats = VehicleStatus(), NodeStats()

    def due(t_s: float) -> list:
        return _origin_msgs(tel.due(round(t_s * 1e6), st, stats))

    boot = due(0.0)
    assert {msg.id for msg in boot} == ORIGIN  # at boot, to whoever listens
    for msg in boot:
        assert (msg.latitude, msg.longitude, msg.altitude) == CMAC
    assert due(1.0) == []
    stats.rx_total = 1  # a ground station's first frame, 2.5 s after boot: origin and home at once
    got = due(2.5)
    assert {msg.id for msg in got} == ORIGIN, "a GCS that appears waits for the periodic origin"
    for t in (2.6, 3.0, 4.0, 5.0, 6.0, 7.0):  # it keeps talking (1 Hz heartbeats): nothing until the period is up
        stats.rx_total += 1
        assert due(t) == []
    stats.rx_total += 1
    assert {msg.id for msg in due(7.5)} == ORIGIN  # the 5 s period, from the last send
    stats.rx_total += 1
    assert due(8.0) == []
    stats.rx_total += 1
    got = due(11.0)  # 3 s without a frame, then one: a (new) GCS appeared
    assert {msg.id for msg in got} == ORIGIN
    assert params.set("ORIGIN_LAT", CMAC[0] + 1000)[0]
    got = due(11.2)  # the origin moved: sent at once with the new value
    assert {msg.id for msg in got} == ORIGIN and all(msg.latitude == CMAC[0] + 1000 for msg in got)
    assert due(11.4) == []


def test_origin_stream_switched_off_stays_off():
    tel = Telemetry(m.MAVLink(None, 1, 1), ParamStore())
    st, stats = VehicleStatus(), NodeStats()
    for msg_id in ORIGIN:
        assert tel.set_interval(msg_id, -1)[0]
    stats.rx_total = 5
    assert _origin_msgs(tel.due(3_000_000, st, stats)) == []


@pytest.mark.parametrize("origin", [(473977420, 85455940), CMAC[:2], (0, 0), (-100, 1799990000),
                                    (800000000, -1200000000)])
def test_a_local_item_sent_as_lat_lon_comes_back_within_a_centimetre(origin):
    lat0, lon0 = origin
    worst = 0.0
    for x_mm in range(0, 40_001, 1237):
        for y_mm in range(0, 25_001, 977):
            north, east = y_mm * frames.LOCAL_ITEM_SCALE // 1000, x_mm * frames.LOCAL_ITEM_SCALE // 1000
            lat, lon = frames.local_item_to_global(north, east, lat0, lon0)
            assert (lat, lon) == frames.world_to_global(x_mm, y_mm, lat0, lon0)
            back = frames.global_to_world(lat, lon, lat0, lon0)
            worst = max(worst, math.dist(back, (x_mm, y_mm)))
    assert worst < 10.0, worst  # 1e-7 deg of latitude is 11.1 mm: half a step each way


def test_a_second_gcs_joining_a_talking_link_gets_the_origin_at_once(tmp_path):
    """The link is not quiet (a first GCS keeps talking), so only the new GCS's heartbeat can tell."""
    from firmware_py.mavlink.dialect import mavlink2 as m2
    from firmware_py.mavlink.node import MavNode
    from firmware_py.mavlink.params import ParamStore
    from firmware_py.mavlink.signing import Signing
    from tests.support.mav_vehicle import TestVehicle

    node = MavNode(TestVehicle(), ParamStore(None), Signing(None))
    node.boot(0)
    first, second = m2.MAVLink(None, 255, 190), m2.MAVLink(None, 250, 190)

    def beat(codec, now):
        msg = codec.heartbeat_encode(m2.MAV_TYPE_GCS, m2.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        msg.pack(codec)
        node.handle(msg, now)

    def origins(now):
        return [x for x in node.tick(now) if x.get_type() in ("GPS_GLOBAL_ORIGIN", "HOME_POSITION")]

    for t in range(0, 3_000_000, 100_000):
        beat(first, t)
        node.tick(t)
    beat(second, 3_000_000)
    assert len(origins(3_000_000)) == 2
