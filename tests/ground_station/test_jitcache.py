"""ground_station/jitcache.py: numba's cache in a folder per version of the sources, so a kernel whose
callee in another file changed is compiled anew (numba alone loads the old machine code)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

from ground_station import jitcache

ROOT = Path(__file__).resolve().parents[2]
CALLER = '''from ground_station.jitcache import numba
from pkg_b.callee import value


@numba.njit(cache=True)
def run():
    return value() + 1
'''
CALLEE = '''from ground_station.jitcache import numba


@numba.njit(cache=True)
def value():
    return {}
'''
RUN = '''import sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])
from ground_station import jitcache
if sys.argv[2] == "jitcache":
    jitcache.configure(Path(sys.argv[1]), ("pkg_a", "pkg_b"))
else:
    jitcache.numba.config.CACHE_DIR = ""  # numba's own: __pycache__ beside each file
from pkg_a.caller import run
print(run())
'''


def _tree(root: Path, value: int) -> None:
    for pkg in ("pkg_a", "pkg_b"):
        (root / pkg).mkdir(parents=True, exist_ok=True)
        (root / pkg / "__init__.py").write_text("")
    (root / "pkg_a" / "caller.py").write_text(CALLER)
    (root / "pkg_b" / "callee.py").write_text(CALLEE.format(value))


def _run(root: Path, mode: str) -> int:
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONDONTWRITEBYTECODE="1")
    env.pop("NUMBA_CACHE_DIR", None)
    done = subprocess.run([sys.executable, "-c", RUN, str(root), mode], capture_output=True, text=True,
                          env=env, timeout=120, check=True)
    return int(done.stdout.split()[-1])


def test_a_changed_callee_in_another_file_is_compiled_anew(tmp_path):
    (tmp_path / "pyproject.toml").write_text("")  # a checkout: the cache goes to .numba_cache
    # numba alone keeps the stale 1 + 1 (should a numba release key the cache on callees too, the first
    # case fails here, and jitcache can go)
    for mode, after_change in (("numba", 2), ("jitcache", 6)):
        root = tmp_path / mode
        _tree(root, 1)
        (root / "pyproject.toml").write_text("")
        assert _run(root, mode) == 2
        time.sleep(0.01)
        (root / "pkg_b" / "callee.py").write_text(CALLEE.format(5))  # the caller's file is untouched
        assert _run(root, mode) == after_change, mode
    folders = sorted(p.name for p in (tmp_path / "jitcache" / ".numba_cache").iterdir())
    assert len(folders) == 2 and all(len(f) == 16 for f in folders)  # one per version of the sources


def test_the_hash_follows_the_sources_and_the_parent_the_place(tmp_path):
    _tree(tmp_path, 1)
    first = jitcache.source_hash(tmp_path, ("pkg_a", "pkg_b"))
    assert jitcache.source_hash(tmp_path, ("pkg_a", "pkg_b")) == first
    (tmp_path / "pkg_b" / "callee.py").write_text(CALLEE.format(2))
    assert jitcache.source_hash(tmp_path, ("pkg_a", "pkg_b")) != first
    assert jitcache.cache_parent(tmp_path, {"XDG_CACHE_HOME": "/x"}) == Path("/x/qnav/numba")  # not a checkout
    (tmp_path / "pyproject.toml").write_text("")
    assert jitcache.cache_parent(tmp_path, {}) == tmp_path / ".numba_cache"
    assert jitcache.cache_parent(tmp_path, {"NUMBA_CACHE_DIR": "/n"}) == Path("/n/qnav")
    assert jitcache.CACHE_FOLDER.parent == jitcache.cache_parent() and jitcache.CACHE_FOLDER.is_dir()
    assert str(jitcache.CACHE_FOLDER) == jitcache.numba.config.CACHE_DIR


def test_other_versions_untouched_for_days_are_pruned_when_a_new_one_is_made(tmp_path, monkeypatch):
    parent = tmp_path / ".numba_cache"
    old, recent = parent / ("0" * 16), parent / ("1" * 16)
    old.mkdir(parents=True)
    recent.mkdir()
    stale = time.time() - (jitcache.PRUNE_DAYS + 1) * 86400
    os.utime(old, (stale, stale))
    _tree(tmp_path, 1)
    (tmp_path / "pyproject.toml").write_text("")
    try:
        with monkeypatch.context() as env:  # the checkout's folder, not one a NUMBA_CACHE_DIR set here names
            env.delenv("NUMBA_CACHE_DIR", raising=False)
            folder = jitcache.configure(tmp_path, ("pkg_a", "pkg_b"))
    finally:
        jitcache.configure()  # this process's kernels stay in the suite's folder
    assert folder.is_dir() and recent.is_dir() and not old.exists()
