"""Issue 29 finding 5: a full disk silently lost acknowledged parameters (the
echo went out, the save failed with one log line, the value was back after a
restart). Now the GCS gets an ERROR STATUSTEXT saying the value will not
survive a reboot, with the save in the handler's thread and on the storage
worker alike; nothing raises out of a handler, and the next good save clears it."""

from __future__ import annotations

import errno

import pytest

from firmware_py.mavlink import params as params_module
from firmware_py.mavlink.dialect import mavlink2 as m
from firmware_py.mavlink.link_thread import StorageWorker
from firmware_py.mavlink.params import ParamStore
from tests.firmware_py.test_mav_engines import Link, of, texts


@pytest.fixture
def full_disk(monkeypatch):
    real = params_module.atomic_write
    state = {"full": True}

    def write(*a, **k):
        if state["full"]:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*a, **k)

    monkeypatch.setattr(params_module, "atomic_write", write)
    return state


@pytest.mark.parametrize("worker", [False, True], ids=["in-handler", "storage-worker"])
def test_a_failed_parameter_save_is_reported_and_the_next_good_one_clears_it(tmp_path, full_disk, worker):
    link = Link(tmp_path)
    if worker:
        link.node.params.deferred = StorageWorker()
    replies = link.send(link.gcs.param_set_encode(1, 1, b"GOAL_TOL_MM", 777, 6))
    assert [p.param_value for p in of(replies, "PARAM_VALUE")] == [777]  # in effect now
    if worker:
        assert link.node.params.deferred.flush()
        replies += link.tick(1000)
    said = [x for x in of(replies, "STATUSTEXT") if x.severity == m.MAV_SEVERITY_ERROR]
    # longer than one STATUSTEXT: chunks sharing an id, as the ground station reassembles them
    assert "".join(x.text for x in said) == "params not saved (No space left on device): lost at reboot"
    assert link.node.params.save_errors == 1 and not link.node.handler_errors
    assert not texts(link.tick(1000))  # reported once
    fresh = ParamStore(tmp_path)
    fresh.load()
    assert fresh.get("GOAL_TOL_MM") != 777  # what the text warned about
    full_disk["full"] = False
    link.send(link.gcs.param_set_encode(1, 1, b"GOAL_TOL_MM", 778, 6))
    if worker:
        assert link.node.params.deferred.flush()
    assert not [t for t in texts(link.tick(1000)) if "not saved" in t or "reboot" in t]
    fresh.load()
    assert fresh.get("GOAL_TOL_MM") == 778
