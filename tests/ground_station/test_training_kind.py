"""The training-kind contract (ground_station.learn.kinds): a kind defined and registered by
the test alone (tests/support/toy_kind.py: its options, trainer and evaluation on the station,
its encoder section and decisions on the robot) is trained by `qnav train`, judged by `qnav
eval`, exported by `qnav export`, loaded by the robot's loader and driven by its controller,
with no change to the CLI, config, trainer, evaluation, export, loader or controller code;
and those modules name no kind.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from firmware_py import kinds as robot_kinds
from firmware_py.policy import load_policy
from ground_station.cli import main
from ground_station.learn import kinds
from ground_station.learn.config import TrainConfig, validate_config
from tests.support import toy_kind

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def toy():
    robot_kinds.register(toy_kind.ROBOT_KIND)
    kinds.register(toy_kind.STATION_KIND)
    try:
        yield
    finally:
        kinds.unregister(toy_kind.NAME)
        toy_kind.unregister_robot_kind(toy_kind.NAME)


def test_a_kind_registered_by_the_test_trains_exports_and_drives_the_robot(toy, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", "--encoding", "toy-spin", "--toy-near-mm", "250", "--steps", "3000", "--lr", "0.2",
                 "--epsilon", "0.2", "--quiet", "--out", str(run)]) == 0
    meta = json.loads((run / "meta.json").read_text())
    assert meta["encoding"] == "toy-spin" and meta["encoder"] == {"near_mm": 250, "kind": "toy-spin"}
    assert meta["config"]["toy_near_mm"] == 250 and "sector_guidance" not in meta["config"]  # its own options only

    assert main(["eval", str(run), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["success_rate"] == 1.0  # the toy learnt its task

    out = tmp_path / "toy.qtab"
    assert main(["export", str(run), "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["encoding"] == "toy-spin" and report["success_rate"] == {"float": 1.0, "int": 1.0}

    pol = load_policy(out.read_bytes())
    assert pol.kind == "toy-spin" and pol.encoder == toy_kind.SpinEncoder(250)
    (clear, _), (blocked, _) = toy_kind.drive(pol)
    assert (clear, blocked) == toy_kind.ACTIONS  # the trained table drives when clear, turns when blocked


def test_the_kinds_options_are_its_own_in_help_config_and_checks(toy, capsys):
    with pytest.raises(SystemExit):
        main(["train", "--encoding", "toy-spin", "--help"])
    text = capsys.readouterr().out
    assert "--toy-near-mm" in text and "--toy-turn-reward" in text
    assert "toy-spin = clear or blocked ahead" in text  # --encoding lists every registered kind's summary
    assert "--sector-guidance" not in text and "--targets" not in text and "--learner-lambda" not in text
    cfg = TrainConfig.of(encoding="toy-spin", toy_near_mm=180)
    assert cfg.options == toy_kind.SpinOptions(near_mm=180) and cfg.flat()["toy_near_mm"] == 180
    with pytest.raises(ValueError, match="sector_guidance: not a training option of the toy-spin encoding"):
        TrainConfig.of(encoding="toy-spin", sector_guidance="path")
    with pytest.raises(ValueError, match="learner sarsa is not implemented for the toy-spin encoding"):
        validate_config(TrainConfig.of(encoding="toy-spin", learner="sarsa"))


def test_an_unregistered_kind_is_refused_by_name(toy, tmp_path):
    kinds.unregister(toy_kind.NAME)
    with pytest.raises(ValueError, match="encoding must be one of cell, sector, sector-memory, got 'toy-spin'"):
        TrainConfig.of(encoding="toy-spin")
    kinds.register(toy_kind.STATION_KIND)
    with pytest.raises(ValueError, match="is registered already"):
        kinds.register(toy_kind.STATION_KIND.__class__(**{**toy_kind.STATION_KIND.__dict__, "summary": "x"}))


GENERIC = ["ground_station/learn/train.py", "ground_station/learn/evaluate.py", "ground_station/learn/export.py",
           "ground_station/learn/config.py", "ground_station/lab/sweep.py",
           "ground_station/commands/train.py", "ground_station/commands/eval.py",
           "ground_station/commands/export.py", "ground_station/commands/policy.py"]


@pytest.mark.parametrize("module", GENERIC)
def test_the_generic_training_modules_name_no_kind(module):
    """A kind-specific branch (an encoder class, a kind's name, isinstance on an encoder) in these
    modules would break the contract: kinds are reached through the registries only."""
    code = "\n".join(line.split("#")[0] for line in (ROOT / module).read_text().splitlines()
                     if not line.lstrip().startswith(("#", '"', "'")))
    named = re.findall(r"CellEncoder|SectorEncoder|GridBugEncoder|isinstance\([^)]*encoder"
                       r"|[\"'](cell|sector|sector-memory)[\"']", code)
    assert named == [], f"{module} names a kind: {named}"
