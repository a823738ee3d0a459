"""The layering of the three packages, enforced from their import statements.

Every `import` / `from ... import` in firmware_py, ground_station and
sim_bridge counts, wherever it sits (module level, inside a function, under
`if TYPE_CHECKING:`): a lazy import is still a dependency. The rules:

* no import cycle among the modules of the three packages;
* only the CLI (`ground_station/cli.py`, `ground_station/commands/`, and the
  `python -m ground_station` entry point) imports the CLI: library code never
  climbs up into a subcommand;
* `firmware_py.control` and `firmware_py.mavlink` never import each other:
  they meet only through the vehicle seam (`firmware_py.vehicle`,
  `firmware_py.plugins`);
* nothing outside `ground_station.lab` imports it but the `qnav bench`, `study`
  and `sweep` subcommands;
* only `ground_station.jitcache` imports numba (in the packages, tests/ and tools/): a kernel
  cached by numba must be defined after it chose the cache folder for these sources;
* firmware_py imports only the stdlib, python-can, cantools, pymavlink and
  pyserial (it runs on the robot), and the optional extra dronecan (only in the
  dronecan backends: firmware_py/dronecan_engine.py, firmware_py/drives/dronecan.py). `test_firmware_isolation.py` checks the
  same boundary at run time, after the imports actually execute.

The graph has one edge per import statement target: `import a.b` and
`from a import b` (b a submodule) point at `a.b`, `from a import name` (name
defined in `a`) points at `a`. Parent packages are not implied edges: the
`__init__` of a package is an edge only when it is named.
"""

from __future__ import annotations

import ast
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("firmware_py", "ground_station", "sim_bridge")

# Third-party top-level import names the robot may use (pyserial imports as `serial`).
FIRMWARE_THIRD_PARTY = frozenset({"can", "cantools", "pymavlink", "serial"})
# the optional extra `qnav[dronecan]`, and the only modules that may import it (a profile naming a
# dronecan backend loads them; `pip install qnav` alone runs every other profile)
FIRMWARE_OPTIONAL = {"dronecan": frozenset({"firmware_py.dronecan_engine", "firmware_py.drives.dronecan"})}


def _module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, pathlib.Path]:
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            found[_module_name(path)] = path
    return found


MODULES = _modules()


def _imports(module: str, path: pathlib.Path) -> list[tuple[str, int]]:
    """(imported module, line) for every import statement in `path`, relative ones resolved."""
    is_package = path.name == "__init__.py"
    tree = ast.parse(path.read_text(), str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((alias.name, node.lineno) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                package = module.split(".")
                if not is_package:
                    package.pop()
                package = package[: len(package) - (node.level - 1)]
                base = ".".join(package + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                found.append((submodule if submodule in MODULES else base, node.lineno))
    return found


IMPORTS = {module: _imports(module, path) for module, path in MODULES.items()}


def _edges() -> dict[str, set[str]]:
    """Module -> modules of the three packages it imports (self-imports dropped)."""
    graph: dict[str, set[str]] = {module: set() for module in MODULES}
    for module, targets in IMPORTS.items():
        for target, _line in targets:
            if target in MODULES and target != module:
                graph[module].add(target)
    return graph


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as a path [a, b, ..., a], or None. Iterative DFS with colours."""
    white, grey, black = 0, 1, 2
    colour = dict.fromkeys(graph, white)
    for start in sorted(graph):
        if colour[start] != white:
            continue
        stack = [(start, iter(sorted(graph[start])))]
        path = [start]
        colour[start] = grey
        while stack:
            node, children = stack[-1]
            child = next(children, None)
            if child is None:
                colour[node] = black
                stack.pop()
                path.pop()
            elif colour[child] == grey:
                return path[path.index(child):] + [child]
            elif colour[child] == white:
                colour[child] = grey
                stack.append((child, iter(sorted(graph[child]))))
                path.append(child)
    return None


def _is_cli(module: str) -> bool:
    return module in ("ground_station.cli", "ground_station.commands") or module.startswith(
        "ground_station.commands."
    )


def _where(module: str, line: int) -> str:
    return f"{MODULES[module].relative_to(ROOT)}:{line}"


def test_the_graph_sees_the_packages_and_their_imports():
    assert {"firmware_py.vehicle", "ground_station.cli", "sim_bridge.plant"} <= set(MODULES)
    assert sum(len(v) for v in _edges().values()) > 100


def test_cycle_finder_reports_the_path():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _find_cycle(graph) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_cycles():
    cycle = _find_cycle(_edges())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_only_the_cli_imports_the_cli():
    # `python -m ground_station` is the CLI's own entry point.
    allowed_importers = {"ground_station.__main__"}
    bad = []
    for module, targets in IMPORTS.items():
        if _is_cli(module) or module in allowed_importers:
            continue
        for target, line in targets:
            if not _is_cli(target):
                continue
            bad.append(f"{_where(module, line)} imports {target}")
    assert not bad, "library code imports the CLI:\n" + "\n".join(bad)


def test_control_and_mavlink_meet_only_through_the_vehicle_seam():
    sides = ("firmware_py.control", "firmware_py.mavlink")
    bad = []
    for module, targets in IMPORTS.items():
        for side, other in (sides, sides[::-1]):
            if module != side and not module.startswith(side + "."):
                continue
            bad.extend(
                f"{_where(module, line)} imports {target}"
                for target, line in targets
                if target == other or target.startswith(other + ".")
            )
    assert not bad, "control and mavlink import each other:\n" + "\n".join(bad)


LAB = "ground_station.lab"
LAB_ENTRY_POINTS = frozenset({"ground_station.commands.bench", "ground_station.commands.study",
                              "ground_station.commands.sweep"})  # the thin subcommands that start it


def test_nothing_outside_the_lab_imports_it():
    """Benches, fault suites, rigs and research live beside the product (ground_station/lab): the
    robot, the sim and the rest of the station run without them."""
    bad = [
        f"{_where(module, line)} imports {target}"
        for module, targets in IMPORTS.items()
        if not (module == LAB or module.startswith(LAB + ".")) and module not in LAB_ENTRY_POINTS
        for target, line in targets
        if target == LAB or target.startswith(LAB + ".")
    ]
    assert not bad, "the product imports the lab:\n" + "\n".join(bad)


def test_firmware_imports_only_stdlib_and_the_robot_dependencies():
    allowed = set(sys.stdlib_module_names) | FIRMWARE_THIRD_PARTY | {"firmware_py"}
    bad = [
        f"{_where(module, line)} imports {target}"
        for module, targets in IMPORTS.items()
        if module.split(".")[0] == "firmware_py"
        for target, line in targets
        if target.split(".")[0] not in allowed
        and module not in FIRMWARE_OPTIONAL.get(target.split(".")[0], ())
    ]
    assert not bad, "firmware_py imports outside its allowed dependencies:\n" + "\n".join(bad)


def test_the_robot_program_runs_without_numpy_where_the_station_has_it():
    """`qnav-robot` as the HIL rigs start it (processes.qnav_robot), with MAVLink on, in this environment
    where numpy is installed: it runs as on the robot (firmware_py.cli.program), loading pymavlink's
    mavutil but never numpy (pymavlink's numpy-only extras left out)."""
    import subprocess

    from ground_station.processes import qnav_robot
    from ground_station.subprocs import free_udp_port

    argv = qnav_robot("--can", "virtual:no-numpy", "--policy", "policies:sector", "--mavlink",
                      f"udpout:127.0.0.1:{free_udp_port()}", "--duration", "0.3", "-q")
    run = subprocess.run([argv[0], "-X", "importtime", *argv[1:]], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr[-2000:]
    loaded = {line.rsplit("|", 1)[-1].strip() for line in run.stderr.splitlines() if line.startswith("import time:")}
    assert "pymavlink.mavutil" in loaded and "firmware_py.mavlink.node" in loaded, sorted(loaded)[:50]
    # importtime lists the barred attempt as "numpy" (microseconds); numpy itself loads numpy._core etc.
    assert not {m for m in loaded if m.startswith("numpy.")}, "the robot program loaded numpy"


def test_only_jitcache_imports_numba():
    """numba keys a cached kernel on its own file's timestamp, not its callees' (ground_station/jitcache.py):
    a module importing numba itself would cache its kernels beside its file, stale once a callee changes."""
    paths = list(MODULES.values()) + sorted((ROOT / "tests").rglob("*.py")) + sorted((ROOT / "tools").rglob("*.py"))
    bad = []
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            bad += [f"{path.relative_to(ROOT)}:{node.lineno} imports {n}" for n in names if n.split(".")[0] == "numba"]
    assert [b for b in bad if not b.startswith("ground_station/jitcache.py:")] == [], bad
    assert any(b.startswith("ground_station/jitcache.py:") for b in bad)  # the scan sees imports


def _architecture_tree() -> list[str]:
    text = (ROOT / "docs" / "architecture.md").read_text()
    block = text[text.index("## The tree"):]
    block = block[block.index("```") + 3:]
    return block[:block.index("```")].splitlines()


def test_the_architecture_tree_names_what_exists():
    """docs/architecture.md's tree: every folder and top-level module it names under a program
    exists, and every package of the three programs is named (the docs follow the code)."""
    top = None
    named: set[str] = set()
    for line in _architecture_tree():
        if line[:1].strip():  # a program or top folder, e.g. "firmware_py/"
            top = line.split()[0].rstrip("/")
            continue
        if top not in ("firmware_py", "ground_station", "sim_bridge"):
            continue
        first = line[2:].split("  ")[0] if line.startswith("  ") and not line.startswith("   ") else ""
        for token in first.split():
            if token.endswith("/"):
                named.add(f"{top}/{token.rstrip('/')}")
                assert (ROOT / top / token).is_dir(), f"docs/architecture.md names {top}/{token}, which is gone"
            elif token.endswith(".py") or token.endswith(".dbc"):
                assert (ROOT / top / token).is_file(), f"docs/architecture.md names {top}/{token}, which is gone"
    for prog in ("firmware_py", "ground_station", "sim_bridge"):
        for init in sorted((ROOT / prog).glob("*/__init__.py")):
            pkg = f"{prog}/{init.parent.name}"
            assert pkg in named, f"{pkg} is not in docs/architecture.md's tree"


def test_product_code_never_imports_tools_or_tests():
    bad = [(m, t, line) for m, targets in IMPORTS.items() for t, line in targets
           if t.split(".")[0] in ("tools", "tests")]
    assert bad == [], f"product code imports tools/ or tests/: {bad}"


def test_learning_does_not_import_navigation():
    """ground_station.learn (training, twins, evaluation) sits below ground_station.nav (the
    navigation bench and the ground station's re-planner), never the other way up."""
    bad = [(m, t, line) for m, targets in IMPORTS.items() if m.startswith("ground_station.learn")
           for t, line in targets if t.startswith("ground_station.nav")]
    assert bad == [], f"learn/ imports nav/: {bad}"
