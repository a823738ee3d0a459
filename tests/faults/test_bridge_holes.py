"""The Foxglove live bridge as a back door (issue 43, finding 2), in paced HIL:
hub + qnav-sim --realtime + qnav-robot --sim-clock, the real `qnav monitor
--plain --foxglove` and a stock WebSocket client. A page's Origin
(http://evil.example) is refused (HTTP 403) and the robot, armed in Hold,
stays in Hold without moving; so with the read-only default, without the
token, and for a goal published (or a position target sent) in Hold; the
positive control, a goal published in Guided, drives the robot."""

import pytest

from ground_station.lab.faults import bridge_holes

pytestmark = pytest.mark.wallclock  # paced HIL (qnav-sim --realtime), watched on the wall clock

pytest.importorskip("websockets", reason="the dev extra's websockets package is the stock client here")


@pytest.mark.slow  # the wall-clock pass's longest (~40 s): first, beside the others
@pytest.mark.timeout(420)
def test_a_page_cannot_drive_the_robot_through_the_bridge_and_a_guided_goal_still_does():
    res = bridge_holes.bridge_holes(len(bridge_holes.CASES), seed=0)
    assert res.tried == len(bridge_holes.CASES)
    assert res.lost == 0, res.failures
    clients = res.figures["clients"]
    assert clients["evil_origin_hold"] == "refused: HTTP 403"
    assert clients["no_token_guided"] == "refused: HTTP 401"
    assert clients["guided_goal"].startswith("published")
    moved = res.figures["moved_m"]
    assert moved["evil_origin_hold"] <= bridge_holes.STILL_M and moved["guided_goal"] > bridge_holes.MOVED_M
