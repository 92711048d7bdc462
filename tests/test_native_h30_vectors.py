"""The stored merge kernels in the host's widest vectors (issue 16, session 30).

LLVM tunes Intel's AVX-512 cores to prefer 256-bit vectors; the merge kernels, bound by
their vector arithmetic, ran 13–25 % faster in 512-bit ones. numba reads its CPU
features once per process, so :mod:`mehs.synthesis._native_child` compiles the stored
kernels in a child process given ``-prefer-256-bit``, leaving the parent's numba (and a
user's own numba code) as they were. The numbers must stay numba's to the bit.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import threading

import numpy as np
import pytest
from _checks import assert_same_merge_bits

from mehs.synthesis import _native, _native_child
from mehs.synthesis.merge import NoiseModel, merge_bracket


def _host_avx512() -> bool:
    import llvmlite.binding as ll

    return bool(ll.get_host_cpu_features().get("avx512f"))


@pytest.fixture()
def fresh(tmp_path, monkeypatch):
    """A cache of its own, and this process's memo and key forgotten."""
    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path / "cache"))
    for k in ("MEHS_KERNEL_VECTORS", "NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setattr(_native, "_loaded", {})
    monkeypatch.setattr(_native, "_children", {})
    monkeypatch.setattr(_native, "_key_base", None)
    return tmp_path / "cache" / "kernels"


def _bracket(seed=3):
    rng = np.random.default_rng(seed)
    E = np.exp(rng.uniform(np.log(0.2), np.log(3000), (7, 40, 5)))
    t = [1.0, 4.0, 16.0]
    stack = [np.clip(np.rint(E * tj + 60 + rng.normal(0, 4, E.shape)), 0, 4095).astype(np.uint16)
             for tj in t]
    stack[2][:2, :5] = 4095                      # censored samples
    return stack, t, [np.full((40, 5), 60.0)] * 3


def _fake_host(monkeypatch, avx512: bool):
    import llvmlite.binding as ll

    class Features(dict):
        def flatten(self):
            return ",".join(("+" if v else "-") + k for k, v in self.items())

    monkeypatch.setattr(ll, "get_host_cpu_features",
                        lambda: Features(avx512f=avx512, avx2=True))


@pytest.mark.parametrize("avx512", [True, False])
def test_the_tuning_follows_the_host_and_yields_to_the_user(fresh, monkeypatch, avx512):
    _fake_host(monkeypatch, avx512)
    assert _native_child.tuning() == ("-prefer-256-bit" if avx512 else "")
    monkeypatch.setenv("MEHS_KERNEL_VECTORS", "256")
    assert _native_child.tuning() == ""
    monkeypatch.delenv("MEHS_KERNEL_VECTORS")
    monkeypatch.setenv("NUMBA_CPU_FEATURES", "+avx2")          # the user's own target
    assert _native_child.tuning() == ""


def test_the_key_tells_tuned_entries_apart(fresh, monkeypatch):
    _fake_host(monkeypatch, True)
    _, tuned = _native._key("poisson_linear", np.dtype(np.uint16), 3)
    monkeypatch.setattr(_native, "_key_base", None)
    monkeypatch.setenv("MEHS_KERNEL_VECTORS", "256")
    _, plain = _native._key("poisson_linear", np.dtype(np.uint16), 3)
    assert tuned != plain


@pytest.mark.parametrize("avx512", [True, False])
def test_the_child_is_given_the_features_and_the_parents_key(fresh, monkeypatch, avx512):
    _fake_host(monkeypatch, avx512)
    seen = {}

    class Popen:
        def __init__(self, argv, env, **kw):
            seen.update(argv=argv, env=env)

    monkeypatch.setattr(subprocess, "Popen", Popen)
    key = _native._key("poisson_linear", np.dtype(np.uint16), 3)[0]
    _native_child.start("poisson_linear", "uint16", 3, fresh / "x.building", key,
                        background=False)
    features = seen["env"].get("NUMBA_CPU_FEATURES")
    if avx512:
        assert features == "+avx512f,+avx2,-prefer-256-bit"
    else:
        assert features is None
    import json

    assert json.loads(seen["argv"][-2]) == key and seen["argv"][-1] == "0"


def test_a_stored_kernel_uses_the_hosts_widest_vectors_and_numbas_bits(fresh, monkeypatch):
    stack, t, darks = _bracket()
    kw = dict(darks=darks, noise=NoiseModel(1.5, 3.0, relative=0.01))
    stored = merge_bracket(stack, t, **kw)
    assert _native.is_stored("poisson_linear", np.uint16, 3)
    (obj,) = fresh.glob("poisson_linear-uint16-P3-*.o")
    objdump = shutil.which("objdump")
    if objdump is not None:
        code = subprocess.run([objdump, "-d", str(obj)], capture_output=True, text=True,
                              check=True).stdout
        assert ("%zmm" in code) == _host_avx512()
    monkeypatch.setenv("MEHS_CACHE_DIR", "")                    # numba's own kernel
    assert_same_merge_bits(stored, merge_bracket(stack, t, **kw))


@pytest.mark.skipif(not hasattr(os, "fork"), reason="the child's lock is POSIX")
def test_a_build_waits_for_another_childs_lock_then_loads(fresh, monkeypatch):
    """Another process compiles the entry: a foreground build waits for it instead of
    compiling a second copy or giving up to numba."""
    import fcntl

    if not _native._base_key()["tuning"]:
        pytest.skip("this host's stored kernels compile in the process itself")
    _, stem = _native._key("poisson_linear_radiance", np.dtype(np.uint16), 3)
    fresh.mkdir(parents=True, exist_ok=True)
    fd = os.open(fresh / f"{stem}.building", os.O_CREAT | os.O_RDWR)
    fcntl.flock(fd, fcntl.LOCK_EX)
    release = threading.Timer(1.5, os.close, (fd,))
    release.start()
    try:
        fn = _native.native_kernel("poisson_linear_radiance", np.uint16, 3)
    finally:
        release.join()
    assert fn is not None


def test_a_failed_child_is_not_started_again_in_this_process(fresh, monkeypatch):
    """(review) each merge started a new child after one failed: seconds a merge"""
    _fake_host(monkeypatch, True)
    started = []

    class Failed:
        def wait(self, timeout=None):
            return 1

    monkeypatch.setattr(_native_child, "start",
                        lambda *a, **k: started.append(a) or Failed())
    for _ in range(3):
        assert _native.native_kernel("poisson_linear", np.uint16, 3) is None
    assert len(started) == 1


def test_a_key_that_cannot_be_made_leaves_the_merge_to_numba(fresh, monkeypatch):
    """(review) llvmlite may raise reading the host's features: no entry, no error"""
    import llvmlite.binding as ll

    def broken(*a):
        raise RuntimeError("failed to get host cpu features")

    monkeypatch.setattr(ll, "get_host_cpu_features", broken)
    assert _native.native_kernel("poisson_linear", np.uint16, 3) is None
    stack, t, darks = _bracket()
    merge_bracket(stack, t, darks=darks)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="the child's lock is POSIX")
@pytest.mark.parametrize("wait", [True, False])
def test_a_stuck_lock_holder_is_waited_for_a_bounded_time(fresh, monkeypatch, wait):
    """(review) a foreground child waited for the lock without limit"""
    import fcntl
    import time

    monkeypatch.setattr(_native, "_in_child", False)
    key, stem = _native._key("poisson_linear", np.dtype(np.uint16), 3)
    monkeypatch.setattr(_native, "_key_base", None)
    monkeypatch.setattr(_native, "LOCK_WAIT_S", 0.3)
    built = []
    monkeypatch.setattr(_native, "native_kernel", lambda *a, **k: built.append(a))
    fresh.mkdir(parents=True, exist_ok=True)
    marker = fresh / f"{stem}.building"
    fd = os.open(marker, os.O_CREAT | os.O_RDWR)
    fcntl.flock(fd, fcntl.LOCK_EX)                  # held "elsewhere", never released
    try:
        t0 = time.monotonic()
        _native._child_build("poisson_linear", np.dtype(np.uint16), 3, str(marker), key,
                             wait=wait)
        waited = time.monotonic() - t0
    finally:
        os.close(fd)
    assert built == ([("poisson_linear", np.dtype(np.uint16), 3)] if wait else [])
    assert waited >= (0.3 if wait else 0.0) and waited < 5.0


def test_a_child_builds_nothing_when_the_sources_changed_since_the_parent_read_them(
        fresh, monkeypatch):
    """(review) the child stored under its own key, which the parent never read"""
    monkeypatch.setattr(_native, "_in_child", False)
    key, _ = _native._key("poisson_linear", np.dtype(np.uint16), 3)
    monkeypatch.setattr(_native, "_key_base", None)
    built = []
    monkeypatch.setattr(_native, "native_kernel", lambda *a, **k: built.append(a))
    stale = dict(key, sources="0" * 64)
    _native._child_build("poisson_linear", np.dtype(np.uint16), 3,
                         str(fresh / "x.building"), stale, wait=False)
    assert built == []


def test_a_child_does_not_import_from_the_working_folder(fresh, monkeypatch, tmp_path):
    """(review) ``python -c`` puts the working folder first on the child's path"""
    work = tmp_path / "work"
    work.mkdir()
    ran = tmp_path / "ran"
    (work / "json.py").write_text(f"open({str(ran)!r}, 'w').close()\n"
                                  "raise ImportError('shadowed')\n")
    monkeypatch.chdir(work)
    assert _native.build_in_background("ptc_pass", np.float32)
    assert _native.native_kernel("ptc_pass", np.float32, build=False) is not None
    assert not ran.exists()


def test_no_home_folder_means_no_cache_not_an_error(monkeypatch, tmp_path):
    """(review) Path.home() raises for a container user without one; with no usable
    temporary folder either (else the cache moves there: test_cache_fallback) nothing
    is cached and the merge runs numba's kernel"""
    import tempfile
    from pathlib import Path

    from mehs._cache import cache_dir

    for k in ("MEHS_CACHE_DIR", "XDG_CACHE_HOME"):
        monkeypatch.delenv(k, raising=False)

    def no_home():
        raise RuntimeError("Could not determine home directory.")

    monkeypatch.setattr(Path, "home", staticmethod(no_home))
    (tmp_path / "a-file").write_text("x")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "a-file" / "tmp"))
    assert cache_dir() is None
    assert _native.native_kernel("poisson_linear", np.uint16, 3) is None
    stack, t, darks = _bracket()
    merge_bracket(stack, t, darks=darks)


def test_a_cache_folder_that_cannot_be_entered_is_no_error(fresh, monkeypatch):
    """(review) is_file() raised PermissionError out of building()/build_in_background()"""
    from pathlib import Path

    def denied(self):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "is_file", denied)
    assert _native.building("ptc_pass", np.float32) is False
    assert _native.build_in_background("ptc_pass", np.float32) is False


def test_a_process_that_cannot_link_compiles_nothing(fresh, monkeypatch):
    """(review) Windows: ctypes.CDLL(None) fails, so every process compiled an entry it
    could never load"""
    import ctypes

    def no_process_library(name, *a, **k):
        raise TypeError("expected str, bytes or os.PathLike object, not NoneType")

    monkeypatch.setattr(_native, "_linkable", None)
    monkeypatch.setattr(ctypes, "CDLL", no_process_library)
    compiled = []
    monkeypatch.setattr(_native, "_compile", lambda *a: compiled.append(a))
    monkeypatch.setattr(_native_child, "start", lambda *a, **k: compiled.append(a))
    assert not _native.supported("poisson_linear", np.uint16, 3)
    assert _native.native_kernel("poisson_linear", np.uint16, 3) is None
    assert compiled == [] and not fresh.exists()
    monkeypatch.setattr(_native, "_linkable", None)


def test_a_child_with_another_numba_than_its_key_builds_nothing(fresh, monkeypatch):
    """(review) the child took the parent's versions on trust"""
    monkeypatch.setattr(_native, "_in_child", False)
    key, _ = _native._key("poisson_linear", np.dtype(np.uint16), 3)
    monkeypatch.setattr(_native, "_key_base", None)
    built = []
    monkeypatch.setattr(_native, "native_kernel", lambda *a, **k: built.append(a))
    fresh.mkdir(parents=True, exist_ok=True)
    _native._child_build("poisson_linear", np.dtype(np.uint16), 3,
                         str(fresh / "x.building"), dict(key, numba="0.0.0"), wait=False)
    assert built == []
    _native._child_build("poisson_linear", np.dtype(np.uint16), 3,
                         str(fresh / "x.building"), key, wait=False)
    assert built == [("poisson_linear", np.dtype(np.uint16), 3)]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="a deleted working folder is POSIX")
def test_a_child_started_from_a_deleted_working_folder_still_builds(fresh, monkeypatch,
                                                                     tmp_path):
    """(review) the child's path rewrite called os.getcwd(), which raised there"""
    gone = tmp_path / "gone"
    gone.mkdir()
    monkeypatch.chdir(gone)
    gone.rmdir()
    assert _native.build_in_background("ptc_pass", np.float32)
    assert _native.native_kernel("ptc_pass", np.float32, build=False) is not None
