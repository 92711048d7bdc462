"""Where nothing of the default cache places can be written (a container's user without a
home folder, a package installed read-only), mehs still caches its kernels: in a private
temporary folder."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

import mehs
from mehs import _cache


@pytest.fixture
def temp_root(monkeypatch, tmp_path):
    """A temporary directory of its own, and no MEHS_CACHE_DIR (conftest sets it empty)."""
    root = tmp_path / "tmp"
    root.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(root))
    monkeypatch.delenv("MEHS_CACHE_DIR", raising=False)
    return root


def _not_a_folder(tmp_path: Path) -> Path:
    """A path no one can create, root included: it lies under a regular file."""
    f = tmp_path / "a-file"
    f.write_text("x")
    return f / "cache"


def test_the_default_place_when_it_can_be_written(temp_root, tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert _cache.cache_dir() == tmp_path / "xdg" / "mehs"
    assert (tmp_path / "xdg" / "mehs").is_dir()
    assert not any(temp_root.iterdir())


def test_a_private_temporary_folder_when_the_default_place_cannot_be(temp_root, tmp_path,
                                                                     monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(_not_a_folder(tmp_path)))
    folder = _cache.cache_dir()
    assert folder is not None and folder.parent == temp_root
    assert folder.name == f"mehs-cache-{os.getuid()}"
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    # no home folder at all: the same
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setattr(Path, "home", classmethod(lambda cls: (_ for _ in ()).throw(
        RuntimeError("no home"))))
    assert _cache.cache_dir() == folder


def test_an_explicit_folder_is_taken_as_named_and_empty_means_none(temp_root, tmp_path,
                                                                   monkeypatch):
    monkeypatch.setenv("MEHS_CACHE_DIR", "")
    assert _cache.cache_dir() is None
    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path / "mine"))
    assert _cache.cache_dir() == tmp_path / "mine"
    assert not (tmp_path / "mine").exists()     # created when something is stored
    assert not any(temp_root.iterdir())


def test_a_temporary_folder_someone_else_could_write_is_refused(temp_root, tmp_path,
                                                                monkeypatch):
    """Kernels and pickles loaded from it run as this user: a folder another user made
    first (or may write) is not adopted."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(_not_a_folder(tmp_path)))
    uid = os.getuid()
    shared = temp_root / f"mehs-cache-{uid}"
    shared.mkdir()
    shared.chmod(0o777)
    assert _cache.cache_dir() is None
    shared.rmdir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir(mode=0o700)
    shared.symlink_to(elsewhere)
    assert _cache.cache_dir() is None
    shared.unlink()
    # made by another user: this process's uid is not its owner's
    monkeypatch.setattr(os, "getuid", lambda: uid + 1)
    (temp_root / f"mehs-cache-{uid + 1}").mkdir(mode=0o700)
    assert _cache.cache_dir() is None
    monkeypatch.setattr(os, "getuid", lambda: uid)
    assert _cache.cache_dir() == temp_root / f"mehs-cache-{uid}"


_CHILD = """
import sys
from mehs.synthesis import _cephes, _kernels
import numpy as np
assert abs(_cephes.logf(np.float32(2.0)) - np.log(2.0)) < 1e-6
print(_cephes.logf.stats.cache_hits.get(_cephes.logf.signatures[0], 0),
      _cephes.logf.stats.cache_misses.get(_cephes.logf.signatures[0], 0))
"""


def test_numba_caches_the_kernels_where_it_has_no_folder_of_its_own(tmp_path):
    """A copy of mehs whose ``__pycache__`` cannot be made, in a process whose numba
    user-wide folder cannot be either: importing a kernel module raised numba's "no
    locator available" before. Now the kernels compile once into the mehs cache's
    ``numba/`` (the private temporary folder with ``MEHS_CACHE_DIR`` empty) and a second
    process loads them."""
    pkg = tmp_path / "site"
    shutil.copytree(Path(mehs.__file__).parent, pkg / "mehs",
                    ignore=shutil.ignore_patterns("__pycache__"))
    for d in (pkg / "mehs").rglob("*"):
        if d.is_dir():
            (d / "__pycache__").write_text("not a folder")
    (pkg / "mehs" / "__pycache__").write_text("not a folder")
    root = tmp_path / "tmp"
    root.mkdir()
    env = {**os.environ, "PYTHONPATH": str(pkg), "TMPDIR": str(root),
           "XDG_CACHE_HOME": str(_not_a_folder(tmp_path)), "MEHS_CACHE_DIR": ""}
    env.pop("NUMBA_CACHE_DIR", None)
    runs = []
    for _ in range(2):
        p = subprocess.run([sys.executable, "-c", _CHILD], env=env, cwd=tmp_path,
                           capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, p.stderr[-2000:]
        runs.append(tuple(map(int, p.stdout.split())))
    assert runs == [(0, 1), (1, 0)]          # compiled, then loaded
    folder = root / f"mehs-cache-{os.getuid()}" / "numba"
    assert any(folder.rglob("_cephes.logf-*.nbi"))
