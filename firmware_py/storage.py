"""The robot's file store: one directory tree that the FTP server and the policy/param code may
touch, and nothing outside it.

Owns path resolution (an FTP path is relative to the root, "/" the root as an autopilot's SD card;
`..`, symlinks anywhere in the path, control characters and temporary names are refused with
EACCES), the quota (bytes, files, directories; at most MAX_HOLE_BYTES past a file's end), crash-safe
writes (a hidden temporary name, fsync, `os.replace`, the directory fsynced; leftovers deleted at
start-up), the robot layout (`ACTIVE_POLICY`, `LAST_GOOD_POLICY`, `PARAMS_FILE`) and the policy slot
swap (`promote_policy`, `boot_policy_candidates`). The rules in full: docs/mavlink.md, "FTP paths".

Errors are `StorageError` (an OSError with an errno and a one-line message); the FTP server maps the
errno onto its NAK codes.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from firmware_py.atomic import TEMP_PREFIX, fsync_dir, temp_path

# Robot layout (FTP paths). docs/mavlink.md "FTP paths" describes them.
POLICY_DIR = "/policies"
ACTIVE_POLICY = "/policies/active.qtab"
LAST_GOOD_POLICY = "/policies/last_good.qtab"
PARAMS_DIR = "/params"
PARAMS_FILE = "/params/params.json"
UID_FILE = "/params/uid"  # the robot's own id (AUTOPILOT_VERSION.uid): made once, never written over FTP
MAP_DIR = "/maps"
ACTIVE_MAP = "/maps/active.map"  # the robot's own map (MovingAI text, its cells CELL_SIZE_MM wide): `qnav map upload`
LAST_GOOD_MAP = "/maps/last_good.map"
LAYOUT_DIRS = (POLICY_DIR, PARAMS_DIR, MAP_DIR)

DEFAULT_QUOTA_BYTES = 8 * 1024 * 1024
DEFAULT_QUOTA_FILES = 256  # regular files under the root, temporary files included
DEFAULT_QUOTA_DIRS = 32  # directories under the root (the layout's own included)
MAX_HOLE_BYTES = 64 * 1024  # a write may start at most this far past the end of the file
MAX_PATH_CHARS = 200  # fits one FTP payload with room for "old\0new"


class StorageError(OSError):
    """A refused or failed storage operation: errno + one-line reason."""


@dataclass(frozen=True)
class Entry:
    """One directory entry as the FTP listing shows it."""

    name: str
    is_dir: bool
    size: int
    mtime: int


def ftp_crc32(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """MAVLink FTP's CRC32: zlib's polynomial, initial 0, no final xor.

    Chains like zlib.crc32: ftp_crc32(b, ftp_crc32(a)) == ftp_crc32(a + b).
    """
    return zlib.crc32(data, crc ^ 0xFFFFFFFF) ^ 0xFFFFFFFF


class Upload:
    """A file being written under a temporary name; `commit` makes it visible."""

    def __init__(self, storage: Storage, final: Path, temp: Path, fd: int) -> None:
        self.storage = storage
        self.final = final
        self.temp = temp
        self.fd = fd
        self.size = os.fstat(fd).st_size

    def write(self, offset: int, data: bytes) -> None:
        """Write `data` at `offset`, refusing growth beyond the quota."""
        if self.fd < 0:
            raise StorageError(errno.EBADF, "upload already closed")
        if offset < 0:
            raise StorageError(errno.EINVAL, "negative offset")
        if offset - self.size > MAX_HOLE_BYTES:
            raise StorageError(errno.EINVAL, f"write at {offset} would leave a hole of "
                                             f"{offset - self.size} bytes (max {MAX_HOLE_BYTES})")
        end = offset + len(data)
        growth = max(0, end - self.size)
        self.storage.reserve(growth)
        os.pwrite(self.fd, data, offset)
        self.size = max(self.size, end)

    def commit(self) -> None:
        """fsync, atomically replace the real name, fsync the directory."""
        if self.fd < 0:
            raise StorageError(errno.EBADF, "upload already closed")
        try:
            os.fsync(self.fd)
        finally:
            os.close(self.fd)
            self.fd = -1
        os.replace(self.temp, self.final)
        fsync_dir(self.final.parent)
        self.storage.invalidate_usage()

    def abort(self) -> None:
        """Drop the temporary file; the real name is untouched."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.temp)
        self.storage.invalidate_usage()


class Storage:
    """All robot files live under `root`; see the module docstring."""

    def __init__(self, root: str | os.PathLike[str], quota_bytes: int = DEFAULT_QUOTA_BYTES,
                 make_layout: bool = True, *, quota_files: int = DEFAULT_QUOTA_FILES,
                 quota_dirs: int = DEFAULT_QUOTA_DIRS) -> None:
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)
        self.quota_bytes = int(quota_bytes)
        self.quota_files = int(quota_files)
        self.quota_dirs = int(quota_dirs)
        self._used: int | None = None
        self._counts: tuple[int, int] | None = None  # (files, directories)
        self.removed_temps = self._remove_stale_temps()
        if make_layout:
            for d in LAYOUT_DIRS:
                (self.root / d.lstrip("/")).mkdir(exist_ok=True)

    # --- paths -----------------------------------------------------------------
    def resolve(self, ftp_path: str) -> Path:
        """Host path for `ftp_path`, or StorageError(EACCES) if it could escape."""
        if not isinstance(ftp_path, str) or len(ftp_path) > MAX_PATH_CHARS:
            raise StorageError(errno.ENAMETOOLONG, "path too long")
        if any(ord(c) < 32 or c == "\\" for c in ftp_path):
            raise StorageError(errno.EACCES, f"path {ftp_path!r} has a control character or backslash")
        parts = [p for p in ftp_path.split("/") if p not in ("", ".")]
        for p in parts:
            if p == "..":
                raise StorageError(errno.EACCES, f"path {ftp_path!r} escapes the storage root")
            if p.startswith(TEMP_PREFIX):
                raise StorageError(errno.EACCES, f"path {ftp_path!r} names a temporary file")
        path = self.root
        for p in parts:
            path = path / p
            try:
                st = os.lstat(path)
            except FileNotFoundError:
                break  # the rest does not exist, so it cannot be a symlink either
            except NotADirectoryError as exc:
                raise StorageError(errno.ENOTDIR, f"{ftp_path!r}: a component is not a directory") from exc
            if stat.S_ISLNK(st.st_mode):
                raise StorageError(errno.EACCES, f"path {ftp_path!r} goes through a symlink")
        return self.root.joinpath(*parts)

    def _existing(self, ftp_path: str) -> tuple[Path, os.stat_result]:
        path = self.resolve(ftp_path)
        try:
            return path, os.lstat(path)
        except (FileNotFoundError, NotADirectoryError) as exc:
            raise StorageError(errno.ENOENT, f"{ftp_path!r} not found") from exc

    def _existing_file(self, ftp_path: str) -> Path:
        path, st = self._existing(ftp_path)
        if not stat.S_ISREG(st.st_mode):
            raise StorageError(errno.EISDIR, f"{ftp_path!r} is not a regular file")
        return path

    def _new_file_path(self, ftp_path: str) -> Path:
        path = self.resolve(ftp_path)
        if path == self.root:
            raise StorageError(errno.EISDIR, "cannot write the root directory")
        if not path.parent.is_dir():
            raise StorageError(errno.ENOENT, f"directory of {ftp_path!r} does not exist")
        if path.is_dir():
            raise StorageError(errno.EISDIR, f"{ftp_path!r} is a directory")
        return path

    # --- quota -----------------------------------------------------------------
    def usage(self) -> int:
        """Bytes used under the root (temporary files included)."""
        if self._used is None:
            total = 0
            for dirpath, _dirs, files in os.walk(self.root):
                for f in files:
                    with contextlib.suppress(FileNotFoundError):
                        total += os.lstat(os.path.join(dirpath, f)).st_size
            self._used = total
        return self._used

    def invalidate_usage(self) -> None:
        self._used = None
        self._counts = None

    def counts(self) -> tuple[int, int]:
        """(files, directories) under the root, temporary files included."""
        if self._counts is None:
            files = dirs = 0
            for _dirpath, dnames, fnames in os.walk(self.root):
                files += len(fnames)
                dirs += len(dnames)
            self._counts = (files, dirs)
        return self._counts

    def reserve_entry(self, is_dir: bool) -> None:
        """Account for one more file (or directory), or StorageError(ENOSPC)."""
        files, dirs = self.counts()
        if is_dir and dirs + 1 > self.quota_dirs:
            raise StorageError(errno.ENOSPC, f"storage quota of {self.quota_dirs} directories exceeded")
        if not is_dir and files + 1 > self.quota_files:
            raise StorageError(errno.ENOSPC, f"storage quota of {self.quota_files} files exceeded")
        self._counts = (files, dirs + 1) if is_dir else (files + 1, dirs)

    def reserve(self, nbytes: int) -> None:
        """Account for `nbytes` of growth, or StorageError(ENOSPC)."""
        if nbytes <= 0:
            return
        used = self.usage()
        if used + nbytes > self.quota_bytes:
            raise StorageError(errno.ENOSPC, f"storage quota of {self.quota_bytes} bytes exceeded")
        self._used = used + nbytes

    # --- reading ---------------------------------------------------------------
    def open_read(self, ftp_path: str) -> tuple[int, int]:
        """(fd, size) of an existing regular file, opened without following symlinks."""
        path = self._existing_file(ftp_path)
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
        return fd, os.fstat(fd).st_size

    def read_bytes(self, ftp_path: str) -> bytes:
        fd, _size = self.open_read(ftp_path)
        with os.fdopen(fd, "rb") as f:
            return f.read()

    def size(self, ftp_path: str) -> int:
        return self._existing_file(ftp_path).stat().st_size

    def exists(self, ftp_path: str) -> bool:
        try:
            self._existing(ftp_path)
        except StorageError:
            return False
        return True

    def crc32(self, ftp_path: str) -> int:
        """FTP CRC32 of a whole file."""
        fd, _size = self.open_read(ftp_path)
        crc = 0
        with os.fdopen(fd, "rb") as f:
            while chunk := f.read(65536):
                crc = ftp_crc32(chunk, crc)
        return crc

    def listdir(self, ftp_path: str) -> list[Entry]:
        """Entries of a directory, sorted by name, temporary files hidden."""
        path, st = self._existing(ftp_path)
        if not stat.S_ISDIR(st.st_mode):
            raise StorageError(errno.ENOTDIR, f"{ftp_path!r} is not a directory")
        out = []
        for name in sorted(os.listdir(path)):
            if name.startswith(TEMP_PREFIX):
                continue
            try:
                est = os.lstat(path / name)
            except FileNotFoundError:
                continue
            if stat.S_ISLNK(est.st_mode):
                continue  # never offered, never followed
            out.append(Entry(name, stat.S_ISDIR(est.st_mode),
                             0 if stat.S_ISDIR(est.st_mode) else est.st_size, int(est.st_mtime)))
        return out

    # --- writing ---------------------------------------------------------------
    def begin_write(self, ftp_path: str, keep_contents: bool = False) -> Upload:
        """Start writing `ftp_path` under a temporary name, from the existing file's
        bytes if `keep_contents` (OpenFileWO), else empty (CreateFile)."""
        final = self._new_file_path(ftp_path)
        existing = b""
        if keep_contents and final.exists():
            existing = self.read_bytes(ftp_path)
        temp = temp_path(final)
        self.reserve_entry(is_dir=False)  # the temporary file is a file until it replaces `final`
        try:
            fd = os.open(temp, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
        except OSError:
            self.invalidate_usage()
            raise
        upload = Upload(self, final, temp, fd)
        if existing:
            try:
                upload.write(0, existing)
            except OSError:
                upload.abort()
                raise
        return upload

    def write_atomic(self, ftp_path: str, data: bytes) -> None:
        """Replace `ftp_path` with `data` (temp + fsync + os.replace)."""
        upload = self.begin_write(ftp_path)
        try:
            upload.write(0, data)
        except OSError:
            upload.abort()
            raise
        upload.commit()

    def truncate(self, ftp_path: str, length: int) -> None:
        """Atomically cut (or zero-extend) a file to `length` bytes."""
        if length < 0:
            raise StorageError(errno.EINVAL, "negative length")
        size = self.size(ftp_path)
        if length - size > self.quota_bytes - self.usage():  # checked before anything is allocated
            raise StorageError(errno.ENOSPC, f"truncate to {length} bytes exceeds the storage quota "
                                             f"of {self.quota_bytes} bytes")
        upload = self.begin_write(ftp_path, keep_contents=True)
        try:
            self.reserve(length - upload.size)
            os.ftruncate(upload.fd, length)
            upload.size = length
        except OSError:
            upload.abort()
            raise
        upload.commit()

    def remove(self, ftp_path: str) -> None:
        path = self._existing_file(ftp_path)
        os.unlink(path)
        fsync_dir(path.parent)
        self.invalidate_usage()

    def mkdir(self, ftp_path: str) -> None:
        path = self.resolve(ftp_path)
        if os.path.lexists(path):
            raise StorageError(errno.EEXIST, f"{ftp_path!r} already exists")
        if not path.parent.is_dir():
            raise StorageError(errno.ENOENT, f"parent of {ftp_path!r} does not exist")
        self.reserve_entry(is_dir=True)
        os.mkdir(path)

    def rmdir(self, ftp_path: str) -> None:
        path, st = self._existing(ftp_path)
        if path == self.root:
            raise StorageError(errno.EACCES, "cannot remove the root directory")
        if not stat.S_ISDIR(st.st_mode):
            raise StorageError(errno.ENOTDIR, f"{ftp_path!r} is not a directory")
        if any(True for _ in os.scandir(path)):
            raise StorageError(errno.ENOTEMPTY, f"{ftp_path!r} is not empty")
        os.rmdir(path)
        self.invalidate_usage()

    def rename(self, old: str, new: str) -> None:
        """Atomic rename of a file; an existing file at `new` is replaced."""
        src = self._existing_file(old)
        dst = self._new_file_path(new)
        os.replace(src, dst)
        self.invalidate_usage()  # replacing a file frees one
        fsync_dir(dst.parent)
        if src.parent != dst.parent:
            fsync_dir(src.parent)

    # --- crash recovery --------------------------------------------------------
    def _remove_stale_temps(self) -> int:
        n = 0
        for dirpath, _dirs, files in os.walk(self.root):
            for f in files:
                if f.startswith(TEMP_PREFIX):
                    os.unlink(os.path.join(dirpath, f))
                    n += 1
        return n


# --- policy slots ---------------------------------------------------------------
# `activate(host_path)` -> (ok, reason), or a vehicle.PendingActivation when its slow part
# runs off the caller's thread (then the caller calls `commit_promotion` once it succeeded)
ActivateHook = Callable[[str], Any]


def promote_policy(storage: Storage, ftp_path: str, activate: ActivateHook, active: str = ACTIVE_POLICY,
                   last_good: str = LAST_GOOD_POLICY) -> Any:
    """Activate the policy file at `ftp_path` through the vehicle's hook (`ActivateHook`, above),
    which loads, validates and swaps in the file or refuses it (DRIVING, bad file, wrong sensors):
    only on success are the slots moved; on refusal nothing on disk changes."""
    src = policy_source(storage, ftp_path, active)
    got = activate(str(src))
    if not isinstance(got, tuple):
        return got
    ok, reason = got
    if ok:
        commit_promotion(storage, src, active, last_good)
    return ok, reason


def policy_source(storage: Storage, ftp_path: str, active: str = ACTIVE_POLICY) -> Path:
    """The host path of a file about to be activated (StorageError if it is the active one)."""
    src = storage._existing_file(ftp_path)
    if src == storage.resolve(active):
        raise StorageError(errno.EINVAL, f"file is already {active}")
    return src


def commit_promotion(storage: Storage, src: Path, active_path: str = ACTIVE_POLICY,
                     last_good: str = LAST_GOOD_POLICY) -> None:
    """After a successful activation: the old active file becomes the last-good one,
    then `src` becomes the active one (two atomic renames; a crash between them
    leaves the last-good, which boot loads). For policies and for the robot's map alike."""
    active = storage.resolve(active_path)
    if active.exists():
        os.replace(active, storage.resolve(last_good))
    os.replace(src, active)
    fsync_dir(active.parent)
    if src.parent != active.parent:
        fsync_dir(src.parent)


def _existing_files(storage: Storage, *ftp_paths: str) -> list[str]:
    out = []
    for ftp_path in ftp_paths:
        with contextlib.suppress(StorageError):
            out.append(str(storage._existing_file(ftp_path)))
    return out


def boot_map_candidates(storage: Storage) -> list[str]:
    """The robot's map files to try at boot, newest first: active, then last-known-good."""
    return _existing_files(storage, ACTIVE_MAP, LAST_GOOD_MAP)


def boot_policy_candidates(storage: Storage) -> list[str]:
    """Host paths to try at boot, newest first: active, then last-known-good (the caller
    runs the first one the policy loader accepts)."""
    return _existing_files(storage, ACTIVE_POLICY, LAST_GOOD_POLICY)
