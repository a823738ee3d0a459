"""Issue 15's smaller points that the other tests do not reproduce by their
command: `qnav upload` needs no --mavlink (the README's default, shared by
every MAVLink command), `--steps 1e6`, the README's benchmark row naming
every `qnav bench` subcommand, `run/` git-ignored, no setuptools license
deprecation banner (an SPDX string, no License classifier), and
docs/training.md's `make demo` agreeing with the Makefile."""

from __future__ import annotations

import re
import subprocess
import tomllib
from pathlib import Path

from ground_station.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]
LINK_COMMANDS = [["upload", "p.qtab"], ["arm"], ["param", "list"], ["mission", "download"], ["goal", "1", "1"],
                 ["mode", "auto"]]


def test_upload_takes_the_readme_default_link_like_every_mavlink_command():
    readme_default = re.search(r"string, default `(\S+)`", (ROOT / "README.md").read_text()).group(1)
    parser = build_parser()
    defaults = {" ".join(argv): parser.parse_args(argv).mavlink for argv in LINK_COMMANDS}
    assert set(defaults.values()) == {readme_default}, defaults
    # the monitor leaves --mavlink unset (it also replays) and then connects to the same default
    from ground_station.mavlink.link import DEFAULT_URL

    assert parser.parse_args(["monitor", "--plain"]).mavlink is None and readme_default == DEFAULT_URL


def test_integer_options_take_scientific_notation():
    args = build_parser().parse_args(["train", "--steps", "1e6"])
    assert args.steps == 1_000_000 and isinstance(args.steps, int)


def test_readme_benchmark_row_names_every_bench_subcommand():
    parser = build_parser()
    bench = next(a for a in parser._subparsers._group_actions if "bench" in a.choices).choices["bench"]
    names = set(next(a for a in bench._subparsers._group_actions).choices)
    (row,) = [ln for ln in (ROOT / "README.md").read_text().splitlines() if ln.startswith("| `qnav bench ")]
    listed = set(row.split("`")[1].removeprefix("qnav bench ").replace("\\|", "|").split("|"))
    assert listed == names, f"README lists {sorted(listed)}, `qnav bench` has {sorted(names)}"


def test_run_folder_is_git_ignored(tmp_path):
    ignored = {ln.strip() for ln in (ROOT / ".gitignore").read_text().splitlines()}
    assert "run/" in ignored
    git = subprocess.run(["git", "-C", str(ROOT), "check-ignore", "-q", "run/can.blf"], capture_output=True)
    assert git.returncode in (0, 128), git.stderr  # 128: not a git checkout (an sdist): the line above holds
    if git.returncode != 128:
        assert git.returncode == 0


def test_license_is_an_spdx_string_without_a_license_classifier():
    """setuptools >= 77 prints its deprecation banner for a `license = {text=...}`
    table or a `License ::` classifier; an SPDX expression string has neither."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert isinstance(project["license"], str) and project["license"] == "MIT"
    assert not [c for c in project.get("classifiers", []) if c.startswith("License ::")]


def test_training_md_describes_make_demo_as_the_makefile_runs_it():
    recipe = re.search(r"^demo:.*\n((?:\t.*\n)+)", (ROOT / "Makefile").read_text(), re.M).group(1)
    assert [ln.strip() for ln in recipe.splitlines()] == ["$(BIN)/qnav demo"]  # no training
    text = " ".join((ROOT / "docs" / "training.md").read_text().split())
    assert "`make demo` does not train: it installs the package and runs `qnav demo`" in text
