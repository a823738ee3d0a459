"""firmware_py.storage: rooted paths, quota, crash-safe writes, policy slots."""

import errno
import os
from pathlib import Path

import pytest

from firmware_py.storage import (
    ACTIVE_POLICY,
    LAST_GOOD_POLICY,
    TEMP_PREFIX,
    Storage,
    StorageError,
    boot_policy_candidates,
    ftp_crc32,
    promote_policy,
)


@pytest.fixture
def store(tmp_path):
    return Storage(tmp_path / "root", quota_bytes=10_000)


def test_ftp_crc32_is_the_mavlink_ftp_crc_and_chains():
    assert ftp_crc32(b"123456789") == 0x2DFD2D88
    assert ftp_crc32(b"6789", ftp_crc32(b"12345")) == 0x2DFD2D88
    assert ftp_crc32(b"") == 0


def test_layout_directories_exist(store):
    assert [e.name for e in store.listdir("/")] == ["maps", "params", "policies"]


@pytest.mark.parametrize("path", ["/policies/a.qtab", "policies/a.qtab", "//policies/./a.qtab"])
def test_absolute_and_relative_paths_map_inside_the_root(store, path):
    assert store.resolve(path) == store.root / "policies" / "a.qtab"


def test_host_absolute_paths_stay_inside_the_root(store):
    assert store.resolve("/etc/passwd") == store.root / "etc" / "passwd"
    assert not store.exists("/etc/passwd")
    with pytest.raises(StorageError) as exc:
        store.write_atomic("/etc/passwd", b"x")
    assert exc.value.errno == errno.ENOENT  # no /etc directory in the root, nothing created
    assert not (store.root / "etc").exists()


@pytest.mark.parametrize("path", ["../x", "/policies/../../x", "a/../../b", "..", "/policies/..",
                                  "a\\..\\b", "bad\x01name", f"/policies/{TEMP_PREFIX}a-1"])
def test_escapes_and_odd_names_are_refused(store, path):
    with pytest.raises(StorageError) as exc:
        store.resolve(path)
    assert exc.value.errno == errno.EACCES
    assert str(exc.value)


def test_symlinks_anywhere_in_the_path_are_refused(store, tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret").write_bytes(b"secret")
    os.symlink(outside, store.root / "policies" / "link")
    os.symlink(outside / "secret", store.root / "policies" / "file_link")
    for path in ("/policies/link/secret", "/policies/link/new", "/policies/file_link", "/policies/link"):
        with pytest.raises(StorageError) as exc:
            store.resolve(path)
        assert exc.value.errno == errno.EACCES, path
    with pytest.raises(StorageError):
        store.write_atomic("/policies/link/new", b"x")
    with pytest.raises(StorageError):
        store.read_bytes("/policies/file_link")
    assert sorted(p.name for p in outside.iterdir()) == ["secret"]
    assert [e.name for e in store.listdir("/policies")] == []  # symlinks are not listed


def test_write_atomic_replaces_and_leaves_no_temp(store):
    store.write_atomic("/params/params.json", b"one")
    store.write_atomic("/params/params.json", b"two")
    assert store.read_bytes("/params/params.json") == b"two"
    assert os.listdir(store.root / "params") == ["params.json"]


def test_uncommitted_upload_is_invisible_and_cleaned_at_restart(store):
    store.write_atomic("/policies/a.qtab", b"old")
    up = store.begin_write("/policies/a.qtab")
    up.write(0, b"new but partial")
    assert store.read_bytes("/policies/a.qtab") == b"old"
    assert [e.name for e in store.listdir("/policies")] == ["a.qtab"]
    os.close(up.fd)  # the process dies here: no commit, no abort
    again = Storage(store.root)
    assert again.removed_temps == 1
    assert os.listdir(store.root / "policies") == ["a.qtab"]
    assert again.read_bytes("/policies/a.qtab") == b"old"


def test_quota_counts_everything_and_refuses_growth(store):
    store.write_atomic("/policies/a", b"x" * 6000)
    up = store.begin_write("/policies/b")
    up.write(0, b"y" * 3000)
    with pytest.raises(StorageError) as exc:
        up.write(3000, b"y" * 2000)
    assert exc.value.errno == errno.ENOSPC
    with pytest.raises(StorageError):
        up.write(2**32, b"z")  # a huge offset would be a huge sparse file
    up.abort()
    assert not store.exists("/policies/b")
    assert store.usage() == 6000


def test_truncate_rename_mkdir_rmdir_remove(store):
    store.write_atomic("/policies/a", b"0123456789")
    store.truncate("/policies/a", 4)
    assert store.read_bytes("/policies/a") == b"0123"
    store.mkdir("/policies/sub")
    with pytest.raises(StorageError) as exc:
        store.mkdir("/policies/sub")
    assert exc.value.errno == errno.EEXIST
    store.rename("/policies/a", "/policies/sub/b")
    assert store.read_bytes("/policies/sub/b") == b"0123"
    with pytest.raises(StorageError) as exc:
        store.rmdir("/policies/sub")
    assert exc.value.errno == errno.ENOTEMPTY
    store.remove("/policies/sub/b")
    store.rmdir("/policies/sub")
    with pytest.raises(StorageError):
        store.rmdir("/")
    assert [e.name for e in store.listdir("/policies")] == []


def test_promote_policy_keeps_last_good_and_refusal_changes_nothing(store):
    store.write_atomic("/policies/p1.qtab", b"policy one")
    calls = []

    def hook(path):
        calls.append(path)
        data = Path(path).read_bytes()
        return (b"bad" not in data), ("ok" if b"bad" not in data else "corrupt table")

    assert promote_policy(store, "/policies/p1.qtab", hook) == (True, "ok")
    assert store.read_bytes(ACTIVE_POLICY) == b"policy one"
    assert not store.exists(LAST_GOOD_POLICY)
    store.write_atomic("/policies/p2.qtab", b"policy two")
    assert promote_policy(store, "/policies/p2.qtab", hook)[0]
    assert store.read_bytes(ACTIVE_POLICY) == b"policy two"
    assert store.read_bytes(LAST_GOOD_POLICY) == b"policy one"
    store.write_atomic("/policies/p3.qtab", b"bad policy")
    assert promote_policy(store, "/policies/p3.qtab", hook) == (False, "corrupt table")
    assert store.read_bytes(ACTIVE_POLICY) == b"policy two"
    assert store.read_bytes(LAST_GOOD_POLICY) == b"policy one"
    assert store.exists("/policies/p3.qtab")
    assert calls[0] == str(store.root / "policies" / "p1.qtab")
    assert boot_policy_candidates(store) == [str(store.resolve(ACTIVE_POLICY)),
                                             str(store.resolve(LAST_GOOD_POLICY))]
