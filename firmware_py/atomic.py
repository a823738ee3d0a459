"""Atomic file replacement, the one way every qnav program writes a file.

`atomic_write` writes a temporary file beside the target, fsyncs it, `os.replace`s it over the real
name and fsyncs the directory, so a reader, a crash or a power cut sees the old file or the new one,
never a torn one. Temporary names start with `TEMP_PREFIX`; the robot's storage hides such names
from FTP listings and deletes leftovers at boot.

Stdlib only: firmware_py uses it, and ground_station and sim_bridge import it from here.
"""

from __future__ import annotations

import os
import secrets
from pathlib import Path

TEMP_PREFIX = ".qnav-tmp-"  # hidden from listings, refused as a path component


def temp_path(final: Path) -> Path:
    """A fresh temporary name in `final`'s directory (same filesystem, so os.replace is atomic)."""
    return final.parent / f"{TEMP_PREFIX}{final.name}-{secrets.token_hex(4)}"


def fsync_dir(path: str | os.PathLike[str]) -> None:
    """fsync a directory so a rename or unlink inside it survives a power cut."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike[str], data: bytes | str, *, make_parents: bool = False,
                 mode: int = 0o666) -> None:
    """Replace `path` with `data` (str is written as UTF-8): temp + fsync + os.replace.

    mode: the new file's permissions, less the umask (the default is what any new file gets; 0o600
    keeps a secret private from the first byte). make_parents: create missing parent directories
    first; otherwise a missing directory raises FileNotFoundError.
    """
    final = Path(path)
    if isinstance(data, str):
        data = data.encode()
    if make_parents:
        final.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(final)
    # the mode through os.open lets the kernel apply the umask, as for any new file
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, mode)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(final.parent)
