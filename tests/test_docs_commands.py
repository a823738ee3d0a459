"""Every command line in README.md and docs/*.md, checked against the programs
as built (issue 15: "every command in README and docs run by a test").

Each documented line of `qnav`, `qnav-sim` or `qnav-robot` (fenced code
blocks and inline code) is parsed by the program's own argument parser, so
a flag that was renamed or removed, or a value the program refuses, fails
here. Synopsis lines (placeholders such as FILE, DIR, `A|B`) are checked
after dropping their placeholder parts where that leaves a real command.
The lines that can run on this machine within a test's time are then run
verbatim in a scratch folder (`RUN`); every other line is listed in
`NOT_RUN` with the reason, and a documented line in neither list fails the
test, so new docs get a decision.
"""

from __future__ import annotations

import contextlib
import functools
import io
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PROGRAMS = ("qnav", "qnav-sim", "qnav-robot")
PLACEHOLDER = re.compile(r"^(?:FILE|DIR|URL|S|X|Y|N|NAME|PATH|SPEC|VALUE|SYSID|M|HZ|DEG|MS|COL|ROW|H|SEED|US|"
                         r"KEY|DEV|DEVICE|CH|CHANNEL|PORT|OLD|NEW|MAP|VERB|COMMAND|ACTION|HEADING|LAT|LON)"
                         r"(?:[.|,][A-Za-z0-9_|,.]*)?$|\.\.\.|\\\|")

# documented lines run verbatim here, in this order, in one scratch folder
RUN = [
    "qnav train --map paper10 --encoding cell --targets A,B,C,D --out out/demo",
    "qnav eval out/demo [--json] [--plot out/demo/policy.png]",
    "qnav sweep --map paper10 --encoding cell --lrs 0.1:0.9:0.1 --seeds 20 --steps 10000 --out out/sweep",
    # docs/training.md, sector-memory: the shipped recipe trains in seconds (grid twin)
    "qnav train --encoding sector-memory --map paper10 --seed 0 --out build/policies/sector_memory",
    "qnav eval build/policies/sector_memory --map paper10 --json",
    "qnav eval build/policies/sector_memory --map maze-16x16-s1 --json",
]

_HIL = "a hub + qnav-sim + qnav-robot bring-up on fixed ports; the same commands run on free ports in " \
       "tests/hil/test_hil_transports.py and tests/hil/test_gcs_link_robot.py"
_VCAN = "needs kernel CAN (vcan0/can0); none on this host (tests/hil/test_hil_transports.py runs it in user-mode Linux)"
_ROBOT = "a real robot on a radio or CAN bus"
# documented lines (or their prefix) not run here, and why; they are still parsed
_WALK = "docs/walkthrough.md's steps, run in order as a new user runs them by tests/hil/test_walkthrough.py"
_YOURS = "docs/your-robot.md's steps, run in order by tests/hil/test_your_robot_e2e.py (two robot profiles)"
_WIDE = "results.md's wide-robot policies (full recipes); tests/ground_station/test_bench_profile.py trains them small"
NOT_RUN = {
    "qnav policy revert --mavlink /dev/ttyUSB0": _ROBOT + "; tests/hil/test_policy_revert.py runs it against qnav-robot",
    "make demo": "installs into the shared venv; `qnav demo` runs in tests/hil/test_demo.py",
    "make venv": "the venv this test runs in",
    "qnav train --map warehouse.map": _WALK,
    "qnav eval runs/warehouse": _WALK,
    "qnav export runs/warehouse": _WALK,
    "qnav sitl --map warehouse.map": _WALK,
    "qnav upload warehouse.qtab": _WALK,
    "qnav mission upload --targets B,C,D": _WALK,
    "qnav mode manual": "Manual mode and `qnav drive` in tests/hil/test_sitl.py (a pty for the keys)",
    "qnav drive": "Manual mode and `qnav drive` in tests/hil/test_sitl.py (a pty for the keys)",
    "qnav monitor --plain --until-done": _WALK,
    "qnav report runs/mission.tlog": _WALK,
    # docs/your-robot.md: run block by block by tests/hil/test_your_robot_e2e.py
    "qnav train --map workshop.map": _YOURS,
    "qnav train --recipe shipped-sector --map workshop.map": _YOURS,
    "qnav eval runs/cell --profile": _YOURS,
    "qnav eval runs/sector --profile": _YOURS,
    "qnav export runs/cell --profile": _YOURS,
    "qnav export runs/sector --profile": _YOURS,
    "qnav policy inspect cell.qtab sector.qtab": _YOURS,
    "qnav sitl --profile my_robot.toml": _YOURS,
    "qnav map upload workshop.map": _YOURS,
    "qnav disarm": _YOURS,
    "qnav upload cell.qtab": _YOURS,
    "qnav upload sector.qtab": _YOURS,
    "qnav mission upload --targets B,C,D,A": _YOURS,
    "qnav monitor --plain --until-done --duration 240": _YOURS,
    "qnav report runs/sector.tlog": "the walkthrough's report step (tests/hil/test_walkthrough.py runs it)",
    # docs/results.md §10: the wide robot's policies, trained in ~15 s each (tests/ground_station/
    # test_bench_profile.py and test_train_profile.py train and export them at a small scale)
    "qnav train --recipe shipped-sector --profile": _WIDE,
    "qnav train --recipe shipped-cell --profile": _WIDE,
    "qnav export wide_": _WIDE,
    "make test": "the test suite itself",
    "qnav study --map maze-15x15-s2": "the same study on a second map (~25 s); tests/ground_station/test_study.py "
                                      "runs its code at a small scale",
    "qnav study --out out/study": "the learner study of results.md §1-2 (600 runs, 15 s of CPU); tests/ground_station/"
                                  "test_study.py runs the same command at a small scale",
    "qnav bench train": "a benchmark (about a minute); tests check a benchmark's code, never a time",
    "qnav study --out out/study-sector": "the sector learner study (~2 min on two idle cores); "
                                         "tests/ground_station/test_study.py runs its code at a small scale",
    "qnav-sim --map paper10 --can remote:": _HIL,
    "qnav-robot --can remote:": _HIL,
    "qnav param set FS_GCS_ENABLE 0": _HIL,
    "qnav upload policies/paper10_cell.qtab --activate --mavlink udpin:": _HIL,
    "qnav mission upload --targets A,B,C,D": _HIL,
    "qnav arm": _HIL,
    "qnav mode auto": _HIL,
    "qnav monitor": "a live dashboard or link; tests/ground_station/test_monitor_*.py drive it",
    "qnav-sim   --map paper10 --can socketcan:vcan0": _VCAN,
    "qnav-robot --can socketcan:vcan0": _VCAN,
    "qnav report run/bus.log": _VCAN + " (the log comes from candump on vcan0)",
    "qnav-robot --can socketcan:can0": _ROBOT,
    "qnav-robot --profile firmware_py/profiles/odrive.toml --can socketcan:can0": _ROBOT,
    # docs/deploy.md: a robot's bring-up, its CAN interface and systemd; the same commands against the sim in
    # tests/hil/test_bringup_check.py (--check), tests/firmware_py/test_service_unit.py (the unit, sd_notify)
    # and tests/hil/test_onboard_log.py (qnav log list|pull)
    "qnav-robot --check --profile /etc/qnav/robot.toml --can socketcan:can0": _ROBOT,
    "qnav-robot --print-unit | sudo tee": "writes /etc; tests/firmware_py/test_service_unit.py checks --print-unit",
    "qnav upload my_policy.qtab --activate --mavlink /dev/ttyUSB0": _ROBOT,
    "qnav log list --mavlink /dev/ttyUSB0": _ROBOT,
    "qnav log pull --mavlink /dev/ttyUSB0": _ROBOT,
    "qnav-sim   --profile firmware_py/profiles/odrive.toml --map paper10 --lockstep --can ...":
        "a placeholder bus; tests/hil/test_odrive_drive.py runs qnav-sim and qnav-robot with this profile on a hub",
    "qnav upload policies/paper10_cell.qtab --activate --mavlink /dev/ttyUSB0": _ROBOT,
    "qnav demo": "tests/hil/test_demo.py runs it",
    "qnav log mcap runs/demo-<time>/": "a placeholder run folder; tests/hil/test_demo.py converts a demo's",
    "qnav log mcap session.tlog": "placeholder files; tests/ground_station/test_log_mcap.py converts a tlog",
    "qnav sitl --can socketcan:vcan0": _VCAN + "; tests/hil/test_sitl_vcan.py runs it there",
    "qnav sitl": "stays up until Ctrl-C; tests/hil/test_sitl.py runs it on free ports and drives MAVProxy on it",
    "qnav sweep --map paper10 --encoding cell --lrs 0.1:0.9:0.1 --seeds 20":
        "9 learning rates x 20 seeds and their curves (both cores for seconds, measured in docs/training.md); "
        "the 10 000-step sweep is in RUN",
    "qnav sweep ... --engine ray": "a Ray campaign on 8 workers or a cluster (qnav[cluster]); "
                                   "tests/ground_station/test_campaign.py runs the Ray engine where Ray is installed",
    "qnav bench hil": "a benchmark (minutes of HIL episodes); tests check a benchmark's code, never a time",
    "qnav bench campaign": "a benchmark (200 twin runs per engine); tests check a benchmark's code, never a time",
    "qnav bench nav": "a benchmark (1000 twin / 50 HIL episodes); tests check a benchmark's code, never a time",
    "qnav bench decisions": "a benchmark (hundreds of traced twin episodes); tests/ground_station/"
                            "test_recovery_learning.py checks its classification",
    "qnav bench ceiling": "a benchmark (hundreds of twin episodes and their space-time searches); "
                          "tests/ground_station/test_oracle.py runs it on two episodes and checks the oracle",
    "qnav policy upgrade OLD.qtab": "a synopsis (placeholders); its flags are checked above",
    "qnav export RUN_DIR": "a synopsis (placeholders); its flags are checked above",
    "qnav train --recipe shipped-sector --out build/sector": "the shipped sector recipe (2e7 steps, ~15 s of CPU); "
                                                            "tests/hil/test_new_map_mission.py trains it on a new map",
    "qnav export build/sector --dtype int8 --local-planner --no-preserve-argmax": "needs that run; tests/ground_station/"
                                                                              "test_policy_export.py checks the option",
    "qnav export build/policies/sector_memory": "writes the shipped policies/sector_memory.qtab (tools/make_policy.py "
                                                 "runs it; tests/ground_station/test_policy_shipped.py checks the file)",
}
# Inline examples in prose (`qnav upload --activate`) are parsed and their flags checked, never run.


def _command_lines(body: str) -> list[str]:
    """The qnav/make lines of a code block, continuations joined, comments
    dropped, and the block's own `NAME="..."` shell variables expanded."""
    body = re.sub(r"\\\n\s*", " ", body)
    variables: dict[str, str] = {}
    out = []
    for line in body.splitlines():
        line = re.sub(r"\s+#\s.*$", "", line.strip()).strip()
        var = re.fullmatch(r"([A-Z_][A-Z0-9_]*)=(.*)", line)
        if var:
            variables[var.group(1)] = " ".join(shlex.split(var.group(2)))
            continue
        line = re.sub(r"\$([A-Z_][A-Z0-9_]*)", lambda m: variables.get(m.group(1), m.group(0)), line)
        if re.match(r"(qnav(-sim|-robot)?|make) ", line + " "):
            out.append(line)
    return out


def _documented() -> list[tuple[str, str, bool]]:
    """(where, line, is_command) of every documented command line: shell
    blocks hold command lines; other blocks (synopses) and inline code in
    prose (`qnav upload --activate`) name commands and flags."""
    out = []
    for doc in DOCS:
        text = doc.read_text()
        rel = doc.relative_to(ROOT)
        for block in re.finditer(r"```([^\n]*)\n(.*?)```", text, re.S):
            if block.group(1).strip() == "text":
                continue  # a program's output shown in the docs, not a command line
            shell = block.group(1).strip() in ("sh", "bash", "shell", "console")
            out += [(f"{rel}", line, shell) for line in _command_lines(block.group(2))
                    if "  qnav-robot (robot)" not in line]
        prose = re.sub(r"```.*?```", "", text, flags=re.S)
        # indented (4-space) code blocks hold command lines as shell blocks do (docs/campaigns.md)
        for block in re.finditer(r"(?:^|\n\n)((?:(?: {4}[^\n]*)?\n)+)", prose + "\n"):
            out += [(f"{rel}", line, True) for line in _command_lines(block.group(1))]
        prose = re.sub(r"(?:^|\n\n)(?:(?: {4}[^\n]*)?\n)+", "\n\n", prose + "\n")
        for span in re.finditer(r"`((?:qnav|qnav-sim|qnav-robot) [^`]+)`", prose):
            out.append((f"{rel}", span.group(1).strip(), False))
    return out


def _concrete(line: str) -> list[str] | None:
    """argv of a documented line with optional [...] parts kept unless they
    hold placeholders; None when placeholders remain (a synopsis)."""
    def keep(m: re.Match) -> str:
        inner = m.group(1)
        return "" if any(PLACEHOLDER.search(t) for t in inner.replace("|", " | ").split()) or "|" in inner \
            else inner
    text = re.sub(r"\[([^\[\]]*)\]", keep, line)
    try:
        argv = shlex.split(text.replace("\\|", "|"))
    except ValueError:
        return None
    if any(PLACEHOLDER.search(t) for t in argv) or any("|" in t and not t.startswith(("udp", "tcp")) for t in argv):
        return None
    return argv


@functools.cache
def _parser(program: str):
    """The program's parser, built once per process (qnav's takes ~50 ms to build; parsing leaves it as it was)."""
    if program == "qnav":
        from ground_station.cli import build_parser
    elif program == "qnav-sim":
        from sim_bridge.cli import build_parser
    else:
        from firmware_py.cli import build_parser
    return build_parser()


DOCUMENTED = _documented()


def test_the_docs_hold_commands():
    assert len(DOCUMENTED) > 30
    assert any(line.startswith("qnav-robot") for _, line, _ in DOCUMENTED)


# concrete command lines of the programs in shell blocks: each must parse as written (synopses and prose
# naming a command have their flags checked by test_every_documented_flag_exists)
CONCRETE = [(where, line, argv) for where, line, fenced in DOCUMENTED
            if fenced and (argv := _concrete(line)) is not None and argv[0] in PROGRAMS]
# lines naming one of the programs (synopses and prose too): their --flags must exist
NAMING = [(where, line) for where, line, _ in DOCUMENTED if line.split()[0] in PROGRAMS]


def test_the_docs_hold_concrete_commands():
    assert len(CONCRETE) > 20 and len(NAMING) >= len(CONCRETE)


@pytest.mark.parametrize("where, line, argv", CONCRETE, ids=[f"{w}:{ln[:60]}" for w, ln, _ in CONCRETE])
def test_documented_command_parses(where, line, argv):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            _parser(argv[0]).parse_args(argv[1:])
        except SystemExit as exc:
            pytest.fail(f"{where}: `{line}` is refused by {argv[0]} (exit {exc.code}): {err.getvalue().strip()}")


@pytest.mark.parametrize("where, line", NAMING, ids=[f"{w}:{ln[:60]}" for w, ln in NAMING])
def test_every_documented_flag_exists(where, line):
    """Synopsis lines too: each --flag they name exists on that command."""
    words = line.replace("[", " ").replace("]", " ").replace("\\|", " ").replace("|", " ").split()
    parser = _parser(words[0])
    flags = set()
    for a in parser._actions:
        flags.update(a.option_strings)
    sub = [a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"]
    node, i = parser, 1
    while sub and i < len(words) and words[i] in sub[0].choices:
        node = sub[0].choices[words[i]]
        for a in node._actions:
            flags.update(a.option_strings)
        sub = [a for a in node._actions if a.__class__.__name__ == "_SubParsersAction"]
        i += 1
    for w in words[i:]:
        flag = w.split("=", 1)[0]
        if flag.startswith("--") and re.fullmatch(r"--[a-z][a-z0-9-]*", flag) and flag != "--flag":
            assert flag in flags, f"{where}: `{line}` names {flag}, which `{' '.join(words[:i])}` does not have"


def test_every_fenced_line_is_run_or_says_why_not():
    for where, line, fenced in DOCUMENTED:
        if not fenced or line in RUN:
            continue
        assert any(line.startswith(prefix) for prefix in NOT_RUN), \
            f"{where}: `{line}` is neither run by this test (RUN) nor listed in NOT_RUN with a reason"


def test_not_run_decides_lines_not_whole_programs():
    """Each NOT_RUN entry names a documented command (more than a program
    name, so a new shell line cannot slip through under a catch-all) and
    still matches a documented line."""
    for prefix in NOT_RUN:
        words = prefix.split()
        assert len(words) >= 2 and words[0] in (*PROGRAMS, "make"), f"NOT_RUN `{prefix}` is a catch-all"
        assert any(line.startswith(prefix) for _, line, _ in DOCUMENTED), f"NOT_RUN `{prefix}`: no doc shows it"


def test_indented_and_fenced_blocks_and_their_variables_are_read():
    """docs/campaigns.md's indented blocks, docs/hil.md's sitl/vcan lines and
    docs/training.md's `$COMMON` lines are extracted as shell command lines."""
    shell = {(where, line) for where, line, fenced in DOCUMENTED if fenced}
    assert ("docs/campaigns.md", "qnav bench campaign --runs 200 --json campaign.json") in shell
    assert ("docs/hil.md", "qnav sitl --can socketcan:vcan0") in shell
    assert ("docs/hil.md", "qnav-robot --can socketcan:vcan0 --lockstep --start 0.25,0.25,0 --goal-cell 9,0") \
        in {(w, " ".join(ln.split()[:8])) for w, ln in shell}
    assert not any("$COMMON" in line for _, line in shell)
    (got,) = _command_lines('X="--map paper10 --seed 3"\nqnav train $X \\\n  --out o  # why\n')
    assert got.split() == ["qnav", "train", "--map", "paper10", "--seed", "3", "--out", "o"]


@pytest.mark.slow
def test_runnable_documented_commands_run(tmp_path):
    documented = {line for _, line, _ in DOCUMENTED}
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    for line in RUN:
        assert line in documented, f"RUN names `{line}`, which no doc shows any more"
        argv = _concrete(line)
        assert argv is not None
        exe = [sys.executable, "-m", "ground_station.cli"] if argv[0] == "qnav" else [str(Path(sys.executable).parent / argv[0])]
        proc = subprocess.run(exe + argv[1:], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, f"`{line}` exit {proc.returncode}: {proc.stderr[-2000:]}"
    assert (tmp_path / "out" / "demo" / "policy.png").is_file()
    assert (tmp_path / "out" / "sweep" / "sweep.json").is_file()
    assert (tmp_path / "build" / "policies" / "sector_memory" / "meta.json").is_file()
