"""MAVLink link faults at small counts (issue 9): GCS heartbeats stop (node
core + controller in the lockstep HIL rig, sim clock), a lossy emulated radio
in front of a real `qnav-robot` (uploads and commands), and three ground
stations + 10 Hz telemetry + uploads against qnav-robot driving in qnav-sim.
Times are measured and reported by `qnav bench faults`, never asserted here."""

import pytest

from ground_station.lab.faults import link_faults


def test_gcs_link_loss_failsafe_within_timeout_plus_one_period():
    res = link_faults.link_loss(4, seed=3)
    assert res.tried == 4
    assert res.lost == 0, res.failures


def test_lossy_link_uploads_exact_or_clear_error_and_commands_acked_or_timed_out():
    # 20 % and 40 % loss (+ duplication and reordering) side by side, seeded (seed 4 -> trials
    # 4000, 4001). Per session the scenario checks: active.qtab is the old or the new complete
    # file and the robot runs it; "ok" only if active.qtab is the new file; a refusal or
    # mismatch verdict (exit 3/5) only if it is not; commands ACKed or a clear timeout.
    res = link_faults.lossy_link(2, seed=4, deadline_s=25.0, levels=(0.2, 0.4), commands=1, workers=2)
    assert res.tried == 2
    assert res.lost == 0, res.failures
    sessions = res.figures["sessions"]
    assert [s["loss"] for s in sessions] == [0.2, 0.4] and [s["seed"] for s in sessions] == [4000, 4001]
    for s in sessions:
        assert s.get("upload") in ("ok", "failed"), s
        assert (s["upload"] == "ok") == (s["byte_exact"] and "error" not in s), s
        if s["upload"] == "failed":
            assert s["exit"] in (3, 4, 5) and "\n" not in s["error"], s
        assert s["acked"] + s["timed_out"] == s["commands"], s
        assert s["link_up"]["lost"] > 0 and s["link_down"]["lost"] > 0  # the link did lose frames


@pytest.mark.slow  # 12 s: started among the wall-clock pass's first
@pytest.mark.wallclock  # counts control periods lost on the wall clock
def test_three_clients_telemetry_and_upload_miss_no_control_tick():
    res = link_faults.load(1, seed=5, duration_s=8.0)
    assert res.lost == 0, res.failures
    run = res.figures["runs"][0]
    assert run["overruns"] == 0 and run["ticks"] == run["sim_ticks"]
    assert run["uploads"] >= 1 and run["param_lists"] >= 1
