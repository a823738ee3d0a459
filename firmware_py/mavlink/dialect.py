"""The MAVLink dialect qnav speaks, robot and ground station alike, in one place.

pymavlink's `development`: common.xml plus the microservices MAVLink still marks work in progress
that ground stations already use; qnav needs Standard Modes (AVAILABLE_MODES, CURRENT_MODE,
AVAILABLE_MODES_MONITOR), which QGroundControl asks a generic autopilot for to build its mode menu.
Every common message keeps its id and CRC, so MAVProxy (ardupilotmega) and any common-dialect client
still read everything else.
"""

from __future__ import annotations

from pymavlink.dialects.v20 import development as mavlink2

NAME = "development"  # for mavutil.mavlink_connection(..., dialect=NAME)

__all__ = ["NAME", "mavlink2"]
