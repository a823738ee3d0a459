"""Fault, load and hostile-input scenarios for the robot (issue 9), in one place.

Every scenario is a function `run(count, seed, progress=None) ->
ScenarioResult` that drives the real robot code (controller, RobotNode on a
python-can bus, MAVLink node, FTP server, storage, `qnav-robot` processes)
`count` times and checks one invariant per trial. `tests/faults/` calls them
with small counts (part of `make test`); `qnav bench faults` calls them with
the large counts and writes the table that docs/reliability.md records.

`SCENARIOS` maps a scenario name to its function and default counts; the
modules register themselves when imported by `load_all()`.
"""

from __future__ import annotations

from ground_station.lab.faults.common import SCENARIOS, Scenario, ScenarioResult, register

__all__ = ["SCENARIOS", "Scenario", "ScenarioResult", "load_all", "register"]

MODULES = ("can_faults", "hostile_mav", "crash", "link_faults", "hostile_holes", "runtime_holes", "floods",
           "control_holes", "dronecan_holes", "bridge_holes", "storage_holes")


def load_all() -> dict[str, Scenario]:
    """Import every scenario module (they register themselves) and return the registry."""
    import importlib

    for name in MODULES:
        importlib.import_module(f"ground_station.lab.faults.{name}")
    return SCENARIOS
