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
    key = _native._base_key()
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
