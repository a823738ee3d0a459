"""The `qnav[station]` extra: which imports the ground station and the sim need beyond the robot's.

`pip install qnav` is the robot; `qnav` and `qnav-sim` also need the `station`
extra. Their entry points call `require_station(prog)` first, which refuses with
one line naming what is missing instead of a traceback from deep inside a
command. It looks the modules up without importing them (numba alone takes a
second). Stdlib only: it runs before anything heavy.
"""

from __future__ import annotations

import importlib.util
import sys

INSTALL_HINT = "pip install 'qnav[station]'"

# distribution (pyproject.toml, [project.optional-dependencies] station) -> top-level import name
STATION_IMPORTS: dict[str, str] = {
    "numpy": "numpy",
    "numba": "numba",
    "pymunk": "pymunk",
    "python-can-remote": "can_remote",
    "gymnasium": "gymnasium",
    "matplotlib": "matplotlib",
    "tqdm": "tqdm",
    "textual": "textual",
    "mcap": "mcap",
    "foxglove-sdk": "foxglove",
}


def missing_station_packages() -> list[str]:
    """Distributions of the station extra whose module cannot be found, in pyproject order."""
    missing = []
    for dist, module in STATION_IMPORTS.items():
        try:
            found = importlib.util.find_spec(module) is not None
        except (ImportError, ValueError):  # a broken install, or an import blocker
            found = False
        if not found:
            missing.append(dist)
    return missing


def require_station(prog: str) -> None:
    """Exit 2 with a one-line install hint when a station package is missing."""
    missing = missing_station_packages()
    if missing:
        print(f"{prog}: error: needs the ground station packages (missing: {', '.join(missing)}): "
              f"{INSTALL_HINT}", file=sys.stderr)
        raise SystemExit(2)
