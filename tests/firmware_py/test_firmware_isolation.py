"""firmware_py must stay compact: no numpy, nothing from the other programs."""

import ast
import pathlib
import subprocess
import sys

FIRMWARE = pathlib.Path(__file__).resolve().parents[2] / "firmware_py"
FORBIDDEN = ("numpy", "numba", "ground_station", "sim_bridge", "pymunk", "matplotlib", "gymnasium")


def test_importing_every_firmware_module_pulls_in_no_forbidden_package():
    modules = sorted(
        "firmware_py." + p.relative_to(FIRMWARE).with_suffix("").as_posix().replace("/", ".")
        for p in FIRMWARE.rglob("*.py") if p.name != "__init__.py"
    )
    code = (
        "import importlib, sys\n"
        f"for m in {modules!r}: importlib.import_module(m)\n"
        f"bad = sorted(n for n in sys.modules if n.split('.')[0] in {FORBIDDEN!r})\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"firmware_py imports {out.stdout.strip()}"
    assert len(modules) >= 2


def test_no_forbidden_import_statement_in_firmware_sources():
    for path in FIRMWARE.rglob("*.py"):
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            for name in names:
                assert name.split(".")[0] not in FORBIDDEN, f"{path.name} imports {name}"
