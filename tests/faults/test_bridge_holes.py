"""The Foxglove live bridge as a back door (issue 43, finding 2), in paced HIL:
hub + qnav-sim --realtime + qnav-robot --sim-clock, the real `qnav monitor
--plain --foxglove` and a stock WebSocket client. A page's Origin
(http://evil.example) is refused (HTTP 403) and the robot, armed in Hold,
stays in Hold without moving; so with the read-only default, without the
token, and for a goal published (or a position target sent) in Hold; the
positive control, a goal published in Guided, drives the robot.

The seven cases run on three robots side by side (two refusals by origin, two
by token, then the last three with the positive control), each its own test:
the wall-clock pass's longest otherwise."""

import pytest

from ground_station.lab.faults import bridge_holes

pytestmark = pytest.mark.wallclock  # paced HIL (qnav-sim --realtime), watched on the wall clock

pytest.importorskip("websockets", reason="the dev extra's websockets package is the stock client here")

PARTS = {"origin": (0, 2), "token": (2, 2), "hold_and_the_control": (4, 3)}  # (first case, count) of CASES


@pytest.mark.slow  # the wall-clock pass's longest: first, beside the others
@pytest.mark.timeout(420)
@pytest.mark.parametrize("part", list(PARTS))
def test_a_page_cannot_drive_the_robot_through_the_bridge_and_a_guided_goal_still_does(part):
    first, count = PARTS[part]
    res = bridge_holes.bridge_holes(count, seed=0, first=first)
    assert res.tried == count
    assert res.lost == 0, res.failures
    clients, moved = res.figures["clients"], res.figures["moved_m"]
    cases = bridge_holes.CASES[first:first + count]
    if part == "origin":
        assert cases == ("evil_origin_hold", "evil_origin_guided")
        assert clients["evil_origin_hold"] == "refused: HTTP 403"
        assert moved["evil_origin_hold"] <= bridge_holes.STILL_M
    elif part == "token":
        assert cases == ("read_only_guided", "no_token_guided")
        assert clients["no_token_guided"] == "refused: HTTP 401"
    else:
        assert cases == ("goal_in_hold", "target_in_hold", "guided_goal")
        assert "mode Hold, not Guided" in res.figures["robot_answer_in_hold"]
        assert moved["goal_in_hold"] <= bridge_holes.STILL_M
        assert clients["guided_goal"].startswith("published")
        assert moved["guided_goal"] > bridge_holes.MOVED_M


def test_the_parts_cover_every_case_once():
    covered = [c for first, count in PARTS.values() for c in bridge_holes.CASES[first:first + count]]
    assert sorted(covered) == sorted(bridge_holes.CASES)
