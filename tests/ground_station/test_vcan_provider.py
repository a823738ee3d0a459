"""ground_station/rigs/vcan.py: the way to a kernel vcan0, its exit status
carried back explicitly, its timeout, and the reasons it gives when there is
no way (the HIL scenarios on it: tests/test_hil_transports.py)."""

from __future__ import annotations

import pytest

from ground_station.rigs import vcan as vc


def _vcan() -> vc.Vcan:
    try:
        return vc.find_vcan()
    except vc.VcanUnavailable as exc:
        pytest.skip(f"no kernel vcan0 here: {exc}")


def test_no_way_gives_the_reason(monkeypatch, tmp_path):
    monkeypatch.setenv("QNAV_VCAN", "none")
    with pytest.raises(vc.VcanUnavailable, match="QNAV_VCAN=none"):
        vc.find_vcan()
    monkeypatch.setenv("QNAV_VCAN", "uml")
    monkeypatch.setenv("PATH", str(tmp_path))  # no linux.uml on it
    monkeypatch.setattr(vc, "UML_MODULES", tmp_path / "none")
    with pytest.raises(vc.VcanUnavailable, match=r"user-mode Linux: missing linux\.uml \(Debian package user-mode-linux\)"):
        vc.find_vcan()


@pytest.mark.timeout(120)
def test_work_status_output_and_a_real_vcan0_come_back(tmp_path):
    vcan = _vcan()
    run = vcan.run("ip -br link show vcan0; candump -L vcan0 -n 1 > one.log & sleep 0.5; "
                   "cansend vcan0 123#0102; wait; cat one.log; echo to-stderr >&2; exit 7",
                   tmp_path, cwd=tmp_path, timeout_s=90)
    assert run.exit_status == 7, run.describe()  # the work's status, not UML's
    assert "vcan0" in run.output and "UP" in run.output.split("vcan0", 1)[1].splitlines()[0]
    assert "vcan0 123#0102" in run.output and "to-stderr" in run.output
    assert (tmp_path / "one.log").read_text().strip().endswith("vcan0 123#0102")  # written back


@pytest.mark.timeout(120)
def test_a_hanging_work_is_killed_at_the_timeout(tmp_path):
    vcan = _vcan()
    run = vcan.run("echo started; sleep 600", tmp_path, cwd=tmp_path, timeout_s=6)
    assert run.timed_out and run.exit_status is None
    assert 6 <= run.wall_s < 20
    assert "timed out" in run.describe()
