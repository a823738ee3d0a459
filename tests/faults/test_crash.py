"""Crash safety at a small count (issue 9): kill -9 of a real `qnav-robot`
during an upload, an activation and a stream of parameter saves; after each
the storage holds complete versions only and the restarted robot reports the
policy it should boot. `qnav bench faults` kills it 50 times."""

from ground_station.lab.faults import crash


def test_kill9_during_upload_activation_and_param_saves():
    res = crash.crash_kill9(3, seed=2)
    assert res.tried == 3
    assert res.lost == 0, res.failures
    assert res.figures["actions"] == {"upload": 1, "activate": 1, "params": 1}
