"""Whether the controller may believe its inputs: each sensor input's freshness (its
arrival stamp, or, while its rolling counter has not advanced, the stamp of the
frame where it last did: a sender stuck re-sending one frame goes stale like a
silent one), and the largest encoder count change a wheel can make.
"""

from __future__ import annotations

from firmware_py import robot_spec
from firmware_py.control.io import Inputs
from firmware_py.layout import DEFAULT as DEFAULT_LAYOUT
from firmware_py.layout import Layout

# Encoder plausibility: a wheel cannot turn faster than MAX_WHEEL_SPEED_MM_S; a
# count difference beyond ENC_JUMP_MARGIN x that (plus a few ticks of slack for
# sampling jitter) over the time since the last sample is a broken or forged
# encoder frame.
ENC_JUMP_MARGIN = 2
ENC_JUMP_SLACK_TICKS = 64
_WHEEL_CIRC_NM = robot_spec.wheel_circumference_nm()


def encoder_jump_limit(dt_us: int, layout: Layout = DEFAULT_LAYOUT) -> int:
    """Largest plausible encoder count change (ticks, either wheel) over dt_us:
    ENC_JUMP_MARGIN x full wheel speed plus ENC_JUMP_SLACK_TICKS; more is a jump.
    (mm/s x us is nm: the distance over the wheel's circumference in nm.) The wheel's
    radius and counts per turn are the layout's (the robot profile's)."""
    circ = _WHEEL_CIRC_NM if layout.wheel_radius_mm == robot_spec.WHEEL_RADIUS_MM else \
        robot_spec.wheel_circumference_nm(layout.wheel_radius_mm)
    return (ENC_JUMP_MARGIN * robot_spec.MAX_WHEEL_SPEED_MM_S * dt_us * layout.counts_per_rev
            // circ + ENC_JUMP_SLACK_TICKS)


def encoder_jump(deltas: tuple[int, int], dt_us: int, layout: Layout = DEFAULT_LAYOUT) -> str:
    """Why an encoder sample whose counts moved by `deltas` (left, right) in `dt_us` is implausible
    ("" if it is not)."""
    limit = encoder_jump_limit(dt_us, layout)
    for side, ticks in (("left", deltas[0]), ("right", deltas[1])):
        if abs(ticks) > limit:
            return f"encoder jump: {side} {ticks} ticks/{dt_us // 1000} ms (max {limit})"
    return ""


class InputFreshness:
    """The rolling counters seen per sensor input and the stamp at which each last advanced."""

    def __init__(self) -> None:
        # key -> (counter, stamp of the frame where it last advanced): frozen senders
        self._counter_seen: dict[str, tuple[int, int | None]] = {}

    def note_counters(self, inp: Inputs) -> None:
        """Remember when each sensor's rolling counter last advanced."""
        stamps = {"ranges0": inp.ranges_us[0], "ranges1": inp.ranges_us[1], "enc": inp.enc_us,
                  "bumper": inp.bumper_us, "driver": inp.driver_us}
        for key, ctr in inp.counters.items():
            seen = self._counter_seen.get(key)
            if seen is None or seen[0] != ctr:
                self._counter_seen[key] = (ctr, stamps.get(key))

    def fresh_since(self, inp: Inputs, key: str, stamp: int | None) -> int | None:
        """The input's time for staleness: its stamp, or, while its counter has not advanced,
        the stamp of the frame where it last did."""
        seen = self._counter_seen.get(key)
        if seen is not None and inp.counters.get(key) == seen[0]:
            return seen[1] if seen[1] is None or stamp is None else min(stamp, seen[1])
        return stamp

    def stale(self, inp: Inputs, now_us: int, timeout_us: int, bumper: bool = True) -> list[str]:
        """The sensor inputs older than `timeout_us` ("<name> frozen" when a stuck counter is why);
        `bumper`: the robot has a bumper board (its input counts)."""
        stale = []
        for name, key, stamp in (("ranges0", "ranges0", inp.ranges_us[0]), ("ranges1", "ranges1", inp.ranges_us[1]),
                                 ("encoders", "enc", inp.enc_us), ("bumper", "bumper", inp.bumper_us))[:4 if bumper else 3]:
            t = self.fresh_since(inp, key, stamp)
            if t is None or now_us - t > timeout_us:
                stale.append(name if t == stamp else f"{name} frozen")
        return stale
