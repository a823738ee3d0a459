"""docs/deploy.md against the files it installs (issue 44 item 6).

Every shell block of the page says where it runs (`# on the laptop` / `# on the Pi`) and whether
it was run here: `(tested here)` blocks are run by `test_tested_blocks_run_here` in a scratch root
(sudo dropped; /opt/qnav, /etc/qnav, /usr/local/bin, /etc/systemd/system and the Pi's /tmp moved
under it; scp a copy; the laptop's .venv python is this interpreter), with Debian's own
/usr/bin/python3, as on Raspberry Pi OS Bookworm. The other blocks need the Pi, its CAN HAT,
systemd running or the robot; for them the page and the shipped units are checked for agreeing
with each other: the unit's ExecStart is the venv the page makes, its --profile the file the page
installs, its --storage writable under ProtectSystem=strict, the user in dialout, can0 brought up
at the bit rate the page uses, the service stopped around --check-motors, and `systemd-analyze
verify` passes both units where systemd-analyze is installed (it works without systemd as PID 1).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.robot_venv import check_robot_venv

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "deploy.md"
DEPLOY = ROOT / "firmware_py" / "deploy"
TEXT = DOC.read_text()
WHERE = re.compile(r"# on the (laptop|Pi)\b[^\n]*\((tested here|not run here[^)]*)\)$")
REROOTED = ("/opt/qnav", "/etc/qnav", "/usr/local/bin", "/etc/systemd/system")


def _blocks(lang: tuple[str, ...] = ("sh", "console")) -> list[str]:
    return [m.group(2) for m in re.finditer(r"```([^\n]*)\n(.*?)```", TEXT, re.S) if m.group(1).strip() in lang]


SHELL = _blocks()
TESTED = [b for b in SHELL if "(tested here)" in b.splitlines()[0]]


def _lines(block: str) -> list[str]:
    """Command lines, comments dropped."""
    out = []
    for line in block.splitlines():
        line = re.sub(r"(^|\s+)#\s.*$", "", line).strip()
        if line:
            out.append(line)
    return out


def _unit(path: Path) -> dict[str, dict[str, list[str]]]:
    """A systemd unit file: section -> key -> values (repeated keys kept, continuations joined)."""
    out: dict[str, dict[str, list[str]]] = {}
    section = ""
    for line in re.sub(r"\\\n\s*", " ", path.read_text()).splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = line.strip("[]")
            out.setdefault(section, {})
            continue
        key, _, value = line.partition("=")
        out[section].setdefault(key.strip(), []).append(value.strip())
    return out


ROBOT_UNIT = _unit(DEPLOY / "qnav-robot.service")
CAN_UNIT = _unit(DEPLOY / "qnav-can0.service")


def _venv() -> str:
    values = set(re.findall(r"^QNAV_VENV=(\S+)$", TEXT, re.M))
    assert len(values) == 1, f"docs/deploy.md sets QNAV_VENV to {values}: one venv"
    return values.pop()


def _exec_argv(unit: dict[str, dict[str, list[str]]]) -> list[str]:
    (line,) = [v for v in unit["Service"]["ExecStart"] if v]  # a drop-in's `ExecStart=` reset aside
    return shlex.split(line)


def _robot_args(argv: list[str]):
    from firmware_py.cli import build_parser

    return build_parser().parse_args(argv[1:])


def test_every_shell_block_says_where_it_runs_and_whether_it_was_run_here():
    assert len(SHELL) >= 8
    for block in SHELL:
        first = block.splitlines()[0]
        assert WHERE.fullmatch(first), f"docs/deploy.md: a shell block starting {first!r} does not say " \
                                       "`# on the laptop|Pi ... (tested here)` or `(not run here: why)`"
    assert len(TESTED) >= 4


def test_the_unit_runs_the_venv_the_page_makes_with_the_profile_it_installs():
    argv = _exec_argv(ROBOT_UNIT)
    venv = _venv()
    assert argv[0] == f"{venv}/bin/qnav-robot", argv[0]
    assert "python3 -m venv $QNAV_VENV" in TEXT and "ln -sf $QNAV_VENV/bin/qnav-robot /usr/local/bin/qnav-robot" in TEXT
    # ProtectHome=yes hides /home, /root and /run/user: the program must live elsewhere
    assert ROBOT_UNIT["Service"]["ProtectHome"] == ["yes"]
    assert not argv[0].startswith(("/home/", "/root/", "/run/user/")) and not venv.startswith(("/home", "/root"))
    args = _robot_args(argv)
    installed = re.findall(r"^sudo install -m 644 \S+/profiles/\w+\.toml (\S+)$", TEXT, re.M)
    assert installed == [args.profile] == ["/etc/qnav/robot.toml"], installed
    assert f"sudo install -d -m 755 {Path(args.profile).parent}" in TEXT
    checks = [ln for b in SHELL for ln in _lines(b) if ln.startswith("qnav-robot --check")]
    assert len(checks) == 2 and all(f"--profile {args.profile} " in ln + " " for ln in checks), checks
    assert args.can == "socketcan:can0" and all("--can socketcan:can0" in ln for ln in checks)


def test_the_service_can_write_its_storage_and_only_that():
    args = _robot_args(_exec_argv(ROBOT_UNIT))
    svc = ROBOT_UNIT["Service"]
    assert svc["ProtectSystem"] == ["strict"]
    writable = [f"/var/lib/{d}" for v in svc.get("StateDirectory", []) for d in v.split()]
    writable += [p for v in svc.get("ReadWritePaths", []) for p in v.split()]
    assert any(args.storage == w or args.storage.startswith(w + "/") for w in writable), (args.storage, writable)
    assert "`/var/lib/qnav`" in TEXT and args.storage == "/var/lib/qnav"


def test_the_service_user_is_the_one_the_page_makes_and_is_in_dialout():
    svc = ROBOT_UNIT["Service"]
    (user,), (group,) = svc["User"], svc["Group"]
    assert "dialout" in " ".join(svc["SupplementaryGroups"]).split()
    (useradd,) = [ln for b in SHELL for ln in _lines(b) if "useradd" in ln]
    words = shlex.split(useradd)
    assert words[-1] == user == group and "--user-group" in words and "--system" in words
    assert words[words.index("--groups") + 1].split(",").count("dialout") == 1
    assert words[words.index("--home-dir") + 1] == _robot_args(_exec_argv(ROBOT_UNIT)).storage


def test_the_dropin_for_a_radio_keeps_the_units_paths():
    (ini,) = [b for b in _blocks(("ini",)) if "ExecStart=" in b]
    unit: dict[str, dict[str, list[str]]] = {"Service": {"ExecStart": []}}
    for line in ini.splitlines():
        if line.startswith("ExecStart="):
            unit["Service"]["ExecStart"].append(line.partition("=")[2].strip())
    assert unit["Service"]["ExecStart"][0] == ""  # the reset a drop-in needs before a new ExecStart
    mine, shipped = _exec_argv(unit), _exec_argv(ROBOT_UNIT)
    assert mine[0] == shipped[0]
    a, b = _robot_args(mine), _robot_args(shipped)
    assert (a.profile, a.storage, a.can, a.rt_priority) == (b.profile, b.storage, b.can, b.rt_priority)
    assert a.mavlink == "/dev/ttyUSB0" and a.mavlink_baud == 57600


def test_can0_comes_up_at_the_pages_bit_rate_before_the_service():
    assert "/boot/firmware/config.txt" in TEXT and re.search(r"^dtoverlay=mcp2515-can0,oscillator=\d+,interrupt=\d+$",
                                                             TEXT, re.M)
    (start,) = CAN_UNIT["Service"]["ExecStart"]
    manual = [ln for b in SHELL for ln in _lines(b) if ln.startswith("sudo ip link set can0")]
    assert len(manual) == 1 and manual[0].removeprefix("sudo ") == re.sub(r"^\S*/ip ", "ip ", start), (manual, start)
    assert re.search(r"bitrate (\d+) restart-ms 100$", start)
    assert Path(start.split()[0]).name == "ip" and start.split()[0].startswith("/")
    assert CAN_UNIT["Service"]["Type"] == ["oneshot"] and CAN_UNIT["Service"]["RemainAfterExit"] == ["yes"]
    assert "sys-subsystem-net-devices-can0.device" in CAN_UNIT["Install"]["WantedBy"]
    unit = ROBOT_UNIT["Unit"]
    assert "qnav-can0.service" in " ".join(unit["Wants"]).split() and "qnav-can0.service" in " ".join(unit["After"]).split()
    assert "sudo systemctl enable --now qnav-can0" in TEXT and "sudo systemctl enable --now qnav-robot" in TEXT


def test_the_service_is_stopped_around_check_motors():
    (block,) = [b for b in SHELL if "--check-motors" in b]
    lines = _lines(block)
    i = next(n for n, ln in enumerate(lines) if "--check-motors" in ln)
    assert "sudo systemctl stop qnav-robot" in lines[:i] and "sudo systemctl start qnav-robot" in lines[i + 1:]


def test_the_pages_revert_is_a_real_command():
    from ground_station.cli import build_parser
    from ground_station.commands.policy import run_revert

    (line,) = [ln for b in SHELL for ln in _lines(b) if ln.startswith("qnav policy revert")]
    args = build_parser().parse_args(shlex.split(line)[1:])
    assert args.func is run_revert and args.mavlink == "/dev/ttyUSB0,57600"


def _analyze() -> str:
    exe = shutil.which("systemd-analyze")
    if exe is None:
        reason = "systemd-analyze not installed (Debian package systemd; tools/install_test_deps.sh installs it as root)"
        print(f"skipped: {reason}")
        pytest.skip(reason)
    return exe


def _verify(units: Path, qnav_robot: Path) -> None:
    """`systemd-analyze verify` of the shipped units, ExecStart pointed at `qnav_robot` (verify checks
    that the executable exists). Any complaint about them (an unknown key too, which verify only
    warns about) fails."""
    units.mkdir(parents=True, exist_ok=True)
    venv = _venv()
    for src in DEPLOY.glob("*.service"):
        (units / src.name).write_text(src.read_text().replace(f"{venv}/bin/qnav-robot", str(qnav_robot)))
    names = sorted(str(p) for p in units.glob("*.service"))
    assert len(names) == 2
    proc = subprocess.run([_analyze(), "verify", *names], capture_output=True, text=True, timeout=60)
    mine = [ln for ln in (proc.stdout + proc.stderr).splitlines() if "qnav" in ln]
    assert proc.returncode == 0 and not mine, proc.stdout + proc.stderr


def test_the_units_pass_systemd_analyze_verify(tmp_path):
    stub = tmp_path / "qnav-robot"
    stub.write_text("#!/bin/sh\nexit 0\n")
    stub.chmod(0o755)
    _verify(tmp_path / "units", stub)


def test_verify_catches_a_missing_program(tmp_path):
    """What the check above is worth: a unit whose ExecStart names no program fails verify."""
    units = tmp_path / "units"
    with pytest.raises(AssertionError, match="is not executable"):
        _verify(units, tmp_path / "nowhere" / "qnav-robot")


def _rerooted(block: str, root: Path) -> str:
    """A tested block as run here: sudo dropped, the Pi's paths under `root`, scp a copy."""
    script = re.sub(r"(?m)(^|\|\s*)sudo ", r"\1", block)  # at a line's start or after a pipe
    script = re.sub(r"(?m)^scp ", "cp ", script)
    script = script.replace("pi@robot.local:/tmp/", f"{root}/tmp/").replace(" /tmp/qnav-", f" {root}/tmp/qnav-")
    for prefix in REROOTED:
        script = re.sub(rf"(?<![\w/.~-]){re.escape(prefix)}", f"{root}{prefix}", script)
    script = re.sub(r"(?m)^\.venv/bin/python ", f"{shlex.quote(sys.executable)} ", script)
    leftover = [p for p in (*REROOTED, "pi@", "sudo ") if re.search(rf"(?<![\w/.~-]){re.escape(p)}", script)]
    assert not leftover, f"a tested block still names {leftover} after re-rooting:\n{script}"
    return script


@pytest.mark.slow
@pytest.mark.timeout(420)
def test_tested_blocks_run_here(tmp_path):
    root = tmp_path / "root"
    for d in ("tmp", "opt", "usr/local/bin", "etc/systemd/system"):
        (root / d).mkdir(parents=True)
    py = Path("/usr/bin/python3")
    probe = subprocess.run([str(py), "-c", "import sys, venv, ensurepip; print(sys.version_info >= (3, 11))"],
                           capture_output=True, text=True) if py.exists() else None
    if probe is None or probe.stdout.strip() != "True":
        # the page's python3 is then this interpreter (same version rule); the blocks still run
        print("note: no Debian /usr/bin/python3 >= 3.11 with venv and ensurepip (python3-venv) here: "
              f"the blocks' python3 is {sys.executable}")
        (root / "usr/local/bin/python3").symlink_to(sys.executable)
    src = Path(shutil.copytree(ROOT, tmp_path / "src", ignore=shutil.ignore_patterns(
        ".venv", ".git", "build", "dist", "runs", "out", "__pycache__", "*.egg-info", ".cache", ".pytest_cache",
        ".ruff_cache", ".mypy_cache", ".hypothesis")))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    env["PATH"] = f"{root}/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"  # python3 is Debian's, as on the Pi
    outputs = []
    for block in TESTED:
        where = WHERE.fullmatch(block.splitlines()[0]).group(1)
        script = _rerooted(block, root)
        proc = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=src if where == "laptop" else root,
                              env=env, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, f"block exit {proc.returncode}:\n{script}\n{proc.stdout[-2000:]}{proc.stderr[-3000:]}"
        outputs.append(proc.stdout)
    venv = root / _venv().lstrip("/")
    version = re.search(r"Python (\d+)\.(\d+)\.\d+", "".join(outputs))
    assert version and (int(version.group(1)), int(version.group(2))) >= (3, 11), outputs
    assert os.readlink(root / "usr/local/bin/qnav-robot") == str(venv / "bin/qnav-robot")
    assert f"{root}/usr/local/bin/qnav-robot" in "".join(outputs)  # `command -v`
    units = root / "etc/systemd/system"
    for name in ("qnav-robot.service", "qnav-can0.service"):  # --print-unit and the shipped file agree
        assert (units / name).read_text() == (DEPLOY / name).read_text()
    profile = root / "etc/qnav/robot.toml"
    assert profile.read_text() == (ROOT / "firmware_py/profiles/odrive.toml").read_text()
    # the installed program reads the installed profile (no boards on a virtual bus: exit 1, each MISSING)
    check = subprocess.run([str(root / "usr/local/bin/qnav-robot"), "--check", "--check-listen", "0.3",
                            "--profile", str(profile), "--can", "virtual:deploy-doc"],
                           capture_output=True, text=True, timeout=60, env=env)
    assert check.returncode == 1 and f"profile {profile}: drive odrive" in check.stdout, check.stdout + check.stderr
    assert "MISSING" in check.stdout
    if shutil.which("systemd-analyze"):  # the units again, ExecStart at the venv the page made
        _verify(tmp_path / "verify", venv / "bin/qnav-robot")
    # the venv the page made is qnav without extras: the robot, nothing of the station (the packaging
    # check, here rather than on a second fresh install)
    check_robot_venv(venv / "bin", env, tmp_path)
