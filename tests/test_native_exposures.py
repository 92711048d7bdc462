"""Stored merge kernels of brackets beyond 3 exposures, vectorised (issue 16, session 36).

Beyond 3 exposures LLVM's default tuning left the one-pass kernels' exposure loop rolled,
so their sample loop stayed scalar: 7–11× the time per exposure of a 3-exposure bracket.
:mod:`mehs.synthesis._native_child` compiles those stored kernels in a child process with
LLVM options that unroll it and allow the sample loop's alias checks. The numbers must
stay numba's to the bit.
"""

from __future__ import annotations

import platform
import re
import shutil
import subprocess

import numpy as np
import pytest
from _checks import assert_same_merge_bits

from mehs.synthesis import _native, _native_child
from mehs.synthesis.merge import NoiseModel, merge_bracket


@pytest.fixture()
def fresh(tmp_path, monkeypatch):
    """A cache of its own, and this process's memo and key forgotten."""
    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(_native, "_loaded", {})
    monkeypatch.setattr(_native, "_children", {})
    monkeypatch.setattr(_native, "_key_base", None)
    return tmp_path / "cache" / "kernels"


def test_llvm_options_only_beyond_three_exposures_and_in_the_key(fresh):
    assert _native_child.llvm_options(_native_child.DEFAULT_TUNED_EXPOSURES) == ()
    for P in (4, 16):
        options = _native_child.llvm_options(P)
        assert any(o.startswith("-unroll-threshold=") for o in options)
        assert _native._key("poisson_linear", np.dtype(np.uint16), P)[0]["llvm"] == list(options)
    assert _native._key("poisson_linear", np.dtype(np.uint16), 3)[0]["llvm"] == []


def test_a_child_whose_options_differ_from_the_key_builds_nothing(fresh, monkeypatch):
    """A parent that asked for other LLVM options (another mehs) gets no entry under its
    key from this child: it would not be the code the key names."""
    key = dict(_native._key("poisson_linear", np.dtype(np.uint16), 5)[0], llvm=[])
    fresh.mkdir(parents=True)
    _native._child_build("poisson_linear", np.dtype(np.uint16), 5, str(fresh / "x.building"),
                         key, wait=True)
    assert not list(fresh.glob("*.o"))


def _bracket(P, seed):
    rng = np.random.default_rng(seed)
    E = np.exp(rng.uniform(np.log(0.2), np.log(3000), (3, 40, 8)))
    t = [2.0 ** j for j in range(P)]
    stack = [np.clip(np.rint(E * tj / 2 ** (P - 3) + 60 + rng.normal(0, 4, E.shape)), 0, 4095)
             .astype(np.uint16) for tj in t]
    stack[-1][:2, :5] = 4095                     # censored samples
    return stack, t, [np.full((40, 8), 60.0)] * P


@pytest.mark.parametrize("kind, P, method, bins", [
    ("poisson_linear", 8, "poisson", 1),                 # the default merge
    ("debevec_linear", 5, "debevec", 1),
    ("robertson_linear_binned", 16, "robertson", 4),     # the most exposures, binned
])
def test_a_stored_kernel_of_many_exposures_is_vectorised_with_numbas_bits(
        fresh, monkeypatch, kind, P, method, bins):
    """Its machine code divides in vector registers (before: scalar divisions only), and
    its numbers are those of numba's own kernel, which stays scalar."""
    stack, t, darks = _bracket(P, seed=P)
    kw = dict(method=method, darks=darks, noise=NoiseModel(1.5, 3.0, relative=0.01),
              consistency_bins=bins)
    stored = merge_bracket(stack, t, **kw)
    assert _native.is_stored(kind, np.uint16, P)
    objdump = shutil.which("objdump")
    if objdump is not None and platform.machine().lower() in ("x86_64", "amd64"):
        (obj,) = fresh.glob(f"{kind}-uint16-P{P}-*.o")
        code = subprocess.run([objdump, "-d", str(obj)], capture_output=True, text=True,
                              check=True).stdout
        assert re.search(r"vdivps\s.*%[xyz]mm", code), "no vector division"
    monkeypatch.setenv("MEHS_CACHE_DIR", "")                    # numba's own kernel
    assert_same_merge_bits(stored, merge_bracket(stack, t, **kw))

