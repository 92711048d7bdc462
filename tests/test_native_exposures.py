"""Stored merge kernels of brackets beyond 3 exposures, vectorised (issue 16, session 36).

LLVM's default tuning left the one-pass kernels' exposure loop rolled beyond 3 exposures
(Debevec's and the binned kernels; every kernel from 6), so their sample loop stayed
scalar: 8.5–13× the time per exposure of a 3-exposure bracket.
:mod:`mehs.synthesis._native_child` compiles those stored kernels in a child process with
LLVM options that unroll it and allow the sample loop's alias checks. The numbers must
stay numba's to the bit.
"""

from __future__ import annotations

import platform
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
from _checks import NO_VECTOR_BUILD as _NO_VECTOR_BUILD
from _checks import assert_same_merge_bits

from mehs.synthesis import _native, _native_child
from mehs.synthesis.merge import NoiseModel, merge_bracket


_SKIP_NO_VECTORS = pytest.mark.skipif(_NO_VECTOR_BUILD, reason="numba set to build without "
                                      "vectorisation (NUMBA_CPU_NAME=generic, NUMBA_OPT=0 or "
                                      "NUMBA_BOUNDSCHECK)")


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
    key from this child: it would not be the code the key names. (Run here with the
    child's process-wide effects held back, in case the guard ever fails.)"""
    applied = []
    monkeypatch.setattr(_native_child, "apply_llvm_options", applied.append)
    monkeypatch.setattr(_native, "_in_child", False)
    key = dict(_native._key("poisson_linear", np.dtype(np.uint16), 5)[0], llvm=[])
    fresh.mkdir(parents=True)
    _native._child_build("poisson_linear", np.dtype(np.uint16), 5, str(fresh / "x.building"),
                         key, wait=True)
    assert not list(fresh.glob("*.o")) and not applied


_IR_CHECK = """
import re, sys
import numpy as np, numba
from mehs.synthesis import _native_child
from mehs.synthesis._native_specs import KERNELS
P = int(sys.argv[1])
_native_child.apply_llvm_options(_native_child.llvm_options(P))
f4 = np.float32
nl, nb, ns = 2, 3, 16
for kind in sys.argv[2:]:
    K = KERNELS[kind].dispatcher()
    kernel = numba.njit(nogil=True, error_model="numpy")(K.py_func)
    zs = tuple(np.full((nl, nb, ns), 100 * (j + 1), np.uint16) for j in range(P))
    outs = (np.zeros((nl, nb, ns), f4), np.zeros((nl, ns), f4), np.zeros((nl, ns), np.int32),
            np.zeros((nl, ns), f4), np.zeros((nl, ns), np.int32), np.zeros((nl, ns), np.int32),
            np.zeros((nl, ns), f4))
    head = (zs, np.zeros((P, nb, ns), f4), np.full(nb, 4000, f4), (2.0 ** np.arange(P)).astype(f4))
    if not kind.startswith("poisson"):
        head += (4096, f4(0.5))
    mid = (1.5, np.full(P, 9, f4), 0.0, np.ones(nb, f4), True, True)
    scratch = ((2, tuple(np.zeros(ns, f4) for _ in range(P)), np.zeros(ns, f4),
                np.zeros(ns, np.int32)) if kind.endswith("_binned") else ())
    kernel(*head, *mid, *scratch, *outs)
    (ir,) = kernel.inspect_llvm().values()
    print(kind, len(re.findall(r"fdiv (?:\\w+ )*<\\d+ x float>", ir)),
          len(re.findall(r"fdiv (?:\\w+ )*float", ir)))
"""


@_SKIP_NO_VECTORS
def test_the_options_vectorise_the_one_pass_kernels_at_16_exposures():
    """Every division of one-pass kernels has its vector form (a scalar one remains
    per division for the loop's remainder) when compiled with the options for 16
    exposures, in a process of its own (the options are process-wide). With LLVM's
    defaults none of these three has one (0 of 10, 13, 15); an option a later LLVM no
    longer knows would be ignored without a word and fail here."""
    # the default, and the two largest bodies (the others vectorised alike when checked:
    # twelve kinds at 4–16 exposures, session 36; a compile at 16 exposures takes seconds)
    kinds = ["poisson_linear", "debevec_linear_binned", "robertson_linear_binned"]
    got = subprocess.run([sys.executable, "-c", _IR_CHECK, "16", *kinds], capture_output=True,
                         text=True, timeout=600, check=True).stdout.split("\n")
    counts = {k: (int(v), int(s)) for k, v, s in (line.split() for line in got if line)}
    assert set(counts) == set(kinds)
    for kind, (vector, scalar) in counts.items():
        assert scalar > 0 and vector >= scalar, (kind, vector, scalar)


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
    if (objdump is not None and platform.machine().lower() in ("x86_64", "amd64")
            and not _NO_VECTOR_BUILD):
        (obj,) = fresh.glob(f"{kind}-uint16-P{P}-*.o")
        code = subprocess.run([objdump, "-d", str(obj)], capture_output=True, text=True,
                              check=True).stdout
        assert re.search(r"vdivps\s.*%[xyz]mm", code), "no vector division"
    monkeypatch.setenv("MEHS_CACHE_DIR", "")                    # numba's own kernel
    assert_same_merge_bits(stored, merge_bracket(stack, t, **kw))

