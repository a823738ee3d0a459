"""The one way tests get a kernel vcan0: the provider chain of
ground_station/lab/rigs/vcan.py, or a skip whose reason names each provider tried
and why it failed (printed, and in pytest's -ra summary)."""

from __future__ import annotations

import pytest

from ground_station.lab.rigs.vcan import Vcan, VcanUnavailable, find_vcan


def kernel_vcan() -> Vcan:
    """A working vcan0 provider, or skip the calling test with the reason."""
    try:
        return find_vcan()
    except VcanUnavailable as exc:
        line = f"no kernel vcan0 here: {exc}"
        print(line)
        pytest.skip(line)
