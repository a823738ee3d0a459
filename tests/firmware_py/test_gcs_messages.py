"""Issue 30's ground-station conventions on the robot's MAVLink node: VFR_HUD
streamed (ground speed, compass heading) and an AUTOPILOT_VERSION uid that is the robot's own and survives a reboot."""

from __future__ import annotations

from pymavlink.dialects.v20 import common as m

from firmware_py.storage import UID_FILE
from tests.firmware_py.test_mav_engines import Link, of


def test_vfr_hud_is_streamed_with_speed_and_compass_heading():
    link = Link()
    link.vehicle.st.speed_mm_s = 250
    link.vehicle.st.heading_mrad = 0  # east in the world frame: compass 90
    huds = []
    for _ in range(30):
        huds += of(link.tick(100_000), "VFR_HUD")
    assert huds, "no VFR_HUD in 3 s"
    hud = huds[-1]
    assert abs(hud.groundspeed - 0.25) < 1e-6 and hud.heading == 90


def test_autopilot_version_uid_is_the_robots_own_and_survives_a_reboot(tmp_path):
    def uid(storage):
        link = Link(storage)
        (v,) = of(link.cmd(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_AUTOPILOT_VERSION), "AUTOPILOT_VERSION")
        return v.uid

    first = uid(tmp_path / "a")
    assert first != 0 and (tmp_path / "a" / UID_FILE.lstrip("/")).is_file()
    assert uid(tmp_path / "a") == first  # kept across boots
    assert uid(tmp_path / "b") not in (0, first)  # another robot, another id
