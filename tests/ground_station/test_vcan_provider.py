"""ground_station/lab/rigs/vcan.py: the provider chain (host, installed UML, cached
UML, none), each UML provider's boot health check and the reasons it gives,
the work's exit status carried back explicitly, and its timeout (the HIL
scenarios on it: tests/hil/test_hil_transports.py)."""

from __future__ import annotations

import os

import pytest

from ground_station.lab.rigs import vcan as vc
from tests.support.vcan import kernel_vcan

PANICKING_KERNEL = """#!/bin/sh
echo "Linux version 6.1.0 (fake user-mode Linux for the provider test)"
echo "userspace - ptrace set fp regs failed, errno = 14"
echo "Kernel panic - not syncing: Attempted to kill init! exitcode=0x0000000b"
exit 0
"""


@pytest.fixture
def no_cached_verdicts(monkeypatch):
    """No verdict cached from another test, and none of the search's settings from the environment
    (make test may run with QNAV_VCAN_HIDE set, to see the vcan tests skip)."""
    monkeypatch.setattr(vc, "_health", {})
    monkeypatch.delenv("QNAV_VCAN", raising=False)
    monkeypatch.delenv("QNAV_VCAN_HIDE", raising=False)


def _fake_uml(tmp_path, monkeypatch, kernel_text: str):
    """An installed `linux.uml` (a script) with a CAN module tree, no cached UML."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    kernel = bin_dir / vc.UML_KERNEL
    kernel.write_text(kernel_text)
    kernel.chmod(0o755)
    modules = tmp_path / "modules"
    for m in vc.UML_CAN_MODULES:
        (modules / "6.1.0" / "kernel" / m).parent.mkdir(parents=True, exist_ok=True)
        (modules / "6.1.0" / "kernel" / m).write_bytes(b"")
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setattr(vc, "UML_MODULES", modules)
    monkeypatch.setenv("QNAV_UML_CACHE", str(tmp_path / "no-cache"))
    monkeypatch.setattr(vc, "_host_vcan", lambda channel, create: "this kernel refuses AF_CAN sockets")


def test_no_way_gives_the_reason(monkeypatch, tmp_path, no_cached_verdicts):
    monkeypatch.setenv("QNAV_VCAN", "none")
    with pytest.raises(vc.VcanUnavailable, match="QNAV_VCAN=none"):
        vc.find_vcan()
    monkeypatch.setenv("QNAV_VCAN", "uml")
    monkeypatch.setenv("PATH", str(tmp_path))  # no linux.uml on it
    monkeypatch.setattr(vc, "UML_MODULES", tmp_path / "none")
    with pytest.raises(vc.VcanUnavailable, match=r"uml: missing linux\.uml \(Debian package user-mode-linux\)"):
        vc.find_vcan()
    monkeypatch.setenv("QNAV_VCAN", "qemu")
    with pytest.raises(vc.VcanUnavailable, match=r"QNAV_VCAN='qemu' unknown"):
        vc.find_vcan()


@pytest.mark.timeout(120)
def test_a_kernel_that_panics_at_boot_is_not_chosen_and_the_panic_is_the_reason(
        monkeypatch, tmp_path, no_cached_verdicts):
    _fake_uml(tmp_path, monkeypatch, PANICKING_KERNEL)
    monkeypatch.delenv("QNAV_VCAN", raising=False)
    monkeypatch.delenv("QNAV_VCAN_HIDE", raising=False)
    with pytest.raises(vc.VcanUnavailable) as exc:
        vc.find_vcan()
    text = str(exc.value)
    assert "\n" not in text  # one line for the skip
    parts = dict(p.split(": ", 1) for p in text.split("; "))
    assert list(parts) == ["host", "uml", "uml-cache"]  # every provider tried, in order
    assert "AF_CAN" in parts["host"]
    assert "failed to boot" in parts["uml"] and "Kernel panic - not syncing" in parts["uml"]
    assert "unpacked under" in parts["uml-cache"] and "no-cache" in parts["uml-cache"]
    # the verdict is cached: a second search does not boot again
    calls = []
    monkeypatch.setattr(vc.Vcan, "run", lambda *a, **k: calls.append(a))
    with pytest.raises(vc.VcanUnavailable):
        vc.find_vcan()
    assert calls == []


def test_hidden_providers_are_named_as_hidden(monkeypatch, no_cached_verdicts):
    monkeypatch.delenv("QNAV_VCAN", raising=False)
    monkeypatch.setenv("QNAV_VCAN_HIDE", "host, uml,uml-cache")
    with pytest.raises(vc.VcanUnavailable) as exc:
        vc.find_vcan()
    assert str(exc.value) == ("host: hidden by QNAV_VCAN_HIDE; uml: hidden by QNAV_VCAN_HIDE; "
                              "uml-cache: hidden by QNAV_VCAN_HIDE")


def test_the_skip_line_names_the_providers(monkeypatch, capsys, no_cached_verdicts):
    monkeypatch.delenv("QNAV_VCAN", raising=False)
    monkeypatch.setenv("QNAV_VCAN_HIDE", "host,uml,uml-cache")
    with pytest.raises(pytest.skip.Exception, match="no kernel vcan0 here: host: hidden"):
        kernel_vcan()
    assert "uml-cache: hidden by QNAV_VCAN_HIDE" in capsys.readouterr().out


def test_the_status_command_lists_every_provider(monkeypatch, capsys, no_cached_verdicts):
    monkeypatch.setattr(vc, "provider_reason", lambda where, channel, create=True:
                        None if where == "uml-cache" else f"{where} is absent")
    monkeypatch.delenv("QNAV_VCAN", raising=False)
    monkeypatch.delenv("QNAV_VCAN_HIDE", raising=False)
    assert vc.main([]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[:3] == ["host      no: host is absent", "uml       no: uml is absent", "uml-cache works"]
    assert out[-1] == "chosen: uml-cache"


@pytest.mark.vcan
@pytest.mark.timeout(120)
def test_work_status_output_and_a_real_vcan0_come_back(tmp_path):
    vcan = kernel_vcan()
    run = vcan.run("ip -br link show vcan0; candump -L vcan0 -n 1 > one.log & sleep 0.5; "
                   "cansend vcan0 123#0102; wait; cat one.log; echo to-stderr >&2; exit 7",
                   tmp_path, cwd=tmp_path, timeout_s=90)
    assert run.exit_status == 7, run.describe()  # the work's status, not UML's
    assert "vcan0" in run.output and "UP" in run.output.split("vcan0", 1)[1].splitlines()[0]
    assert "vcan0 123#0102" in run.output and "to-stderr" in run.output
    assert (tmp_path / "one.log").read_text().strip().endswith("vcan0 123#0102")  # written back


@pytest.mark.vcan
@pytest.mark.timeout(120)
def test_a_hanging_work_is_killed_at_the_timeout(tmp_path):
    vcan = kernel_vcan()
    run = vcan.run("echo started; sleep 600", tmp_path, cwd=tmp_path, timeout_s=6)
    assert run.timed_out and run.exit_status is None
    assert 6 <= run.wall_s < 20
    assert "timed out" in run.describe()
