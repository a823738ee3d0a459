"""The demo's MissionWatch on real MAVLink frames (pymavlink packs and parses them): a robot that
holds for good (bumper, or NAV_STALL_S without progress) ends the demo's wait at once instead of
leaving the lockstep run to fill its logs until the mission timeout."""

from __future__ import annotations

from pymavlink.dialects.v20 import common as mav

from ground_station.demo import MissionWatch, _verdict


def _frames(*msgs) -> list:
    robot = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    parser = mav.MAVLink(None)
    return [m for msg in msgs for m in (parser.parse_buffer(msg.pack(robot)) or [])]


def _statustext(text: str):
    return mav.MAVLink_statustext_message(mav.MAV_SEVERITY_WARNING, text.encode(), 0, 0)


def _watch_after(*msgs) -> MissionWatch:
    w = MissionWatch(total=5, target_seqs=[1, 4])
    w.sysid = 1
    w.started()
    for m in _frames(*msgs):
        w.hook(None, m)
    return w


class _NoneDead:
    def dead(self) -> list:
        return []


def test_a_stall_or_the_bumper_ends_the_wait_with_the_robots_words():
    w = _watch_after(_statustext("item 3: stalled: blocked ahead, 412 mm to go"))
    assert _verdict(w, _NoneDead(), deadline=float("inf")) == "stopped: item 3: stalled: blocked ahead, 412 mm to go"
    w = _watch_after(_statustext("bumper pressed"))
    assert _verdict(w, _NoneDead(), deadline=float("inf")) == "stopped: bumper pressed"


def test_progress_notes_and_other_systems_do_not_end_it():
    w = _watch_after(_statustext("item 3: no progress for 5 s, 800 mm to go"),
                     mav.MAVLink_mission_item_reached_message(1))
    assert _verdict(w, _NoneDead(), deadline=float("inf")) == "" and w.targets_reached == 1
    other = MissionWatch(total=5)
    other.sysid = 2  # a second vehicle's stall is not this robot's
    other.started()
    for m in _frames(_statustext("item 3: stalled: blocked ahead, 412 mm to go")):
        other.hook(None, m)
    assert other.stopped == ""
