"""numba for the station's kernels, with its on-disk cache (`cache=True`) in a folder per version of
the sources: every module that compiles a kernel imports numba from here (`from
ground_station.jitcache import numba`; tests/test_layering.py holds every other module to it).

Why: numba keys a cached kernel on its own file's timestamp only. A kernel whose callee changed in
another file (an inlined helper of `ground_station.learn.jit`, `sim_bridge.obstacles.step_movers`, a
constant of `firmware_py.robot_spec` frozen in at compile time) loaded the old machine code, and a
working tree gave other benchmark rows than a fresh clone of the same commit (4 of 120 on `qnav bench
decisions --blocked both`). Here the cache folder is named by a hash of the sources of the three
packages kernels are built from, so any change to them compiles anew, and the same sources in
another process (xdist workers, `qnav` subprocesses, Ray workers) find the same folder.

Where: `<checkout>/.numba_cache/<hash>` in a source checkout (the folder holding pyproject.toml),
else `$XDG_CACHE_HOME/qnav/numba/<hash>` (`~/.cache`); a NUMBA_CACHE_DIR set by the user is the
parent instead. Folders of other versions untouched for `PRUNE_DAYS` go when a new one is made.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import time
from collections.abc import Mapping
from pathlib import Path

import numba

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("ground_station", "sim_bridge", "firmware_py")  # what kernels are compiled from
PRUNE_DAYS = 2


def source_hash(root: Path = ROOT, packages: tuple[str, ...] = PACKAGES) -> str:
    """16 hex digits over the path and bytes of every .py file of `packages` under `root`."""
    h = hashlib.blake2b(digest_size=8)
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            h.update(path.relative_to(root).as_posix().encode() + b"\0")
            h.update(path.read_bytes())
    return h.hexdigest()


def cache_parent(root: Path = ROOT, env: Mapping[str, str] | None = None) -> Path:
    """The folder holding one cache folder per source hash (module docstring)."""
    environ: Mapping[str, str] = os.environ if env is None else env
    if environ.get("NUMBA_CACHE_DIR"):
        return Path(environ["NUMBA_CACHE_DIR"]) / "qnav"
    if (root / "pyproject.toml").is_file() and os.access(root, os.W_OK):
        return root / ".numba_cache"
    return Path(environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "qnav" / "numba"


def _prune(parent: Path, keep: Path, now: float) -> None:
    """Remove the other versions' folders untouched for PRUNE_DAYS (best effort: another process may
    be doing the same)."""
    for old in parent.iterdir():
        try:
            if old != keep and old.is_dir() and now - old.stat().st_mtime > PRUNE_DAYS * 86400:
                shutil.rmtree(old, ignore_errors=True)
        except OSError:
            pass


def configure(root: Path = ROOT, packages: tuple[str, ...] = PACKAGES) -> Path:
    """Point numba's cache at the folder of this version of `packages` (before any `cache=True` kernel
    is defined: numba looks its locator up when the decorator runs) and return it."""
    folder = cache_parent(root) / source_hash(root, packages)
    if not folder.is_dir():
        try:
            folder.mkdir(parents=True, exist_ok=True)
            _prune(folder.parent, folder, time.time())
        except OSError:
            return folder  # not writable: numba falls back to its own places (__pycache__, ~/.cache)
    else:
        with contextlib.suppress(OSError):
            os.utime(folder)  # in use: not pruned by another version's first process
    numba.config.CACHE_DIR = str(folder)
    return folder


CACHE_FOLDER = configure()

__all__ = ["numba", "CACHE_FOLDER", "configure", "source_hash", "cache_parent"]
