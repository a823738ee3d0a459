"""Link floods and garbage while driving in paced HIL (issue 13): hub + qnav-sim
--realtime + qnav-robot --sim-clock, MAVLink over UDP loopback. Each flood
(600 PARAM_SET, 300 PARAM_REQUEST_LIST, 150 CRC32 of a 6 MB file) -> no
FAULT, no missed tick, the robot answers (wall-clock periods lost are
measured and reported; `qnav bench faults` counts them as lost); the
GCS failsafe trips within timeout + one period while malformed frames keep
arriving. Times are reported by `qnav bench faults`, never asserted here."""

import pytest

from ground_station.lab.faults import floods

pytestmark = pytest.mark.wallclock  # paced HIL: a starved robot process trips the 200 ms motor watchdog


@pytest.mark.slow  # 13 s: started among the wall-clock pass's first
def test_each_flood_while_driving_no_fault_no_missed_tick():
    res = floods.floods(3, seed=2)
    assert [f["kind"] for f in res.figures["floods"]] == list(floods.FLOOD_KINDS)
    assert res.lost == 0, res.failures
    assert res.tried == 4  # three floods + the end-of-run check
    robot = res.figures["robot"]
    assert robot["ticks"] == robot["sim_ticks"] and robot["overruns"] == 0
    # the floods reached the robot's link thread and the coalescing storage worker
    assert robot["link_frames"] > 600 and robot["storage_saves"] >= 1
    assert robot["storage_saves"] + robot["storage_coalesced"] >= 100


def test_gcs_failsafe_trips_while_malformed_frames_keep_arriving():
    res = floods.failsafe_garbage(1, seed=3)
    assert res.lost == 0, res.failures
    run = res.figures["runs"][0]
    assert sum(run["garbage_sent"].values()) > 500 and run["garbage_sent"]["nan_mission_item"] > 0
    assert run["failsafe_after_ms"] > floods.FS_TIMEOUT_MS
