"""What the local planner tests (tests/firmware_py/test_localplan.py and
test_replan.py) share: the range status names, the sensor count, the default
planner configuration and a reading from the front sensor alone."""

from __future__ import annotations

from firmware_py import robot_spec
from firmware_py.kinds.sector.config import LocalPlannerConfig

V, FAR, CLOSE, INVALID = (robot_spec.RANGE_VALID, robot_spec.RANGE_TOO_FAR, robot_spec.RANGE_TOO_CLOSE,
                          robot_spec.RANGE_INVALID)
N = robot_spec.SENSOR_COUNT
CFG = LocalPlannerConfig()


def front(mm: int, status: int = V) -> tuple[list[int], list[int]]:
    """Ranges and statuses: the front sensor reads `mm` with `status`, every other one nothing (too far)."""
    return [mm] + [2000] * (N - 1), [status] + [FAR] * (N - 1)
