import os
import stat

import numpy as np
import pytest

from mehs.errors import InputError
from mehs.io.atomic import (atomic_path, sha256_file, sha256_files, write_json_atomic,
                            write_text_atomic)


def test_atomic_write_leaves_no_temp_on_error(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("partial")
            raise RuntimeError("boom")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []


def test_refuses_to_overwrite_raw_capture(tmp_path):
    target = tmp_path / "raw.raw"
    write_text_atomic(target, "first")
    with pytest.raises(InputError, match="refusing to overwrite"):
        write_text_atomic(target, "second", overwrite=False)
    assert target.read_text() == "first"


def test_permissions_follow_umask(tmp_path):
    target = write_json_atomic(tmp_path / "a.json", {"b": 1})
    mode = stat.S_IMODE(os.stat(target).st_mode)
    mask = os.umask(0)
    os.umask(mask)
    assert mode == 0o666 & ~mask
    assert len(sha256_file(target)) == 64


@pytest.mark.parametrize("file_digest", [True, False])
@pytest.mark.parametrize("size", [0, 1, (1 << 18) - 1, 1 << 18, (1 << 18) + 1, 3 << 19])
def test_sha256_file_equals_hashlib(tmp_path, size, file_digest, monkeypatch):
    import hashlib

    if not file_digest:                      # the Python 3.10 path
        monkeypatch.delattr(hashlib, "file_digest", raising=False)
    data = np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8).tobytes()
    p = tmp_path / "f.raw"
    p.write_bytes(data)
    assert sha256_file(p) == hashlib.sha256(data).hexdigest()


@pytest.mark.parametrize("threads", [None, 1, 2, 5])
def test_sha256_files_names_each_files_digest(tmp_path, threads):
    import hashlib

    rng = np.random.default_rng(7)
    sizes = {"b.raw": 3 << 19, "a.hdr": 10, "c/empty": 0, "d.dat": (1 << 18) + 3}
    paths, want = {}, {}
    for name, n in sizes.items():
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        p = tmp_path / name
        p.parent.mkdir(exist_ok=True)
        p.write_bytes(data)
        paths[name], want[name] = p, hashlib.sha256(data).hexdigest()
    got = sha256_files(paths, threads=threads)
    assert got == want
    assert list(got) == list(paths)                 # the caller's order, not the hashing's
    assert sha256_files({}, threads=threads) == {}


@pytest.mark.parametrize("threads", [1, 2])
def test_sha256_files_raises_the_first_unreadable_file_in_order(tmp_path, threads):
    big = tmp_path / "big.raw"
    big.write_bytes(bytes(1 << 20))
    paths = {"x": tmp_path / "missing1", "big": big, "y": tmp_path / "missing2"}
    with pytest.raises(FileNotFoundError) as info:
        sha256_files(paths, threads=threads)
    assert info.value.filename == str(tmp_path / "missing1")


def _log_durability(monkeypatch):
    """Record fsyncs (by the path their descriptor names) and renames, in order."""
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        return real_fsync(fd)

    def replace(a, b, **kw):
        events.append(("replace", os.fspath(a), os.fspath(b)))
        return real_replace(a, b, **kw)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    return events


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc to name descriptors")
def test_every_atomic_write_reaches_the_disk_before_its_name(tmp_path, monkeypatch):
    # An EXR (and PNG, checkpoint, npz) written through atomic_path was renamed
    # without an fsync: after a power loss the new name could hold an empty file.
    from mehs.io.exr import write_exr_rgb

    events = _log_durability(monkeypatch)
    out = tmp_path / "x.exr"
    write_exr_rgb(out, np.ones((4, 5, 3), np.float32))
    renames = [e for e in events if e[0] == "replace"]
    assert len(renames) == 1 and renames[0][2] == str(out)
    tmp = renames[0][1]
    synced = [e[1] for e in events[:events.index(renames[0])] if e[0] == "fsync"]
    assert tmp in synced, events
    # and the folder holding the new name, after the rename
    assert ("fsync", str(tmp_path)) in events[events.index(renames[0]):], events
