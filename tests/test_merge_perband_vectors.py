"""The per-band one-pass merge kernels stay vectorised on every Python numba runs on.

On Python 3.12 and 3.13 (numba 0.68) the censored residuals of the χ² statistic, read
under ``if cm != 0: for j …: if (cm >> j) & 1:``, left numba's reference counts of the
arrays read there unpruned: ``NRT_incref``/``NRT_decref`` calls inside the sample loop,
which LLVM does not vectorise. Every per-band kernel with the statistic ran scalar there,
8–11× its time on Python 3.11 (per-band Poisson 118 against 11 ms a 48-line chunk). The
residuals are now summed unconditionally, each behind a select (same bits).
"""

from __future__ import annotations

import os
import re

import numpy as np
import pytest

_NO_VECTOR_BUILD = any((os.environ.get("NUMBA_CPU_NAME", "").lower() == "generic",
                        os.environ.get("NUMBA_OPT", "").strip() == "0",
                        os.environ.get("NUMBA_BOUNDSCHECK", "").strip() not in ("", "0")))


@pytest.mark.skipif(_NO_VECTOR_BUILD, reason="numba set to build without vectorisation "
                    "(NUMBA_CPU_NAME=generic, NUMBA_OPT=0 or NUMBA_BOUNDSCHECK)")
@pytest.mark.parametrize("name", ["poisson", "debevec"])
def test_the_per_band_kernels_with_the_statistic_are_vectorised(name):
    """Every division has a vector form in the kernel's code and no reference count is
    left in it (numba's own build, compiled afresh: numba shows no code of a cached
    kernel; 3 exposures, which LLVM's default tuning unrolls)."""
    import numba

    from mehs.synthesis import _merge_fused, _merge_fused_weighted
    from mehs.synthesis._native_child import DEFAULT_TUNED_EXPOSURES

    module = _merge_fused if name == "poisson" else _merge_fused_weighted
    entry = getattr(module, f"merge_chunk_{name}_linear")
    kernel = numba.njit(nogil=True, error_model="numpy")(entry.py_func)
    P, nl, nb, ns = DEFAULT_TUNED_EXPOSURES, 2, 3, 16
    f4 = np.float32
    zs = tuple(np.full((nl, nb, ns), 100 * (j + 1), np.uint16) for j in range(P))
    outs = (np.zeros((nl, nb, ns), f4), np.zeros((nl, ns), f4), np.zeros((nl, ns), np.int32),
            np.zeros((nl, ns), f4), np.zeros((nl, ns), np.int32), np.zeros((nl, ns), np.int32),
            np.zeros((nl, ns), f4))
    head = (zs, np.zeros((P, nb, ns), f4), np.full(nb, 4000, f4),
            (4.0 ** np.arange(P)).astype(f4)) + (() if name == "poisson" else (4096, f4(0.5)))
    kernel(*head, 1.5, np.full(P, 9, f4), 0.0, np.ones(nb, f4), True, True, *outs)
    assert outs[0].max() > 0 and outs[2].max() > 0
    (ir,) = kernel.inspect_llvm().values()
    vector = len(re.findall(r"fdiv (?:\w+ )*<\d+ x float>", ir))
    scalar = len(re.findall(r"fdiv (?:\w+ )*float", ir))
    assert scalar > 0 and vector >= scalar, (name, vector, scalar)
    # the arguments' own reference counts (once, at entry and exit) are all numba keeps
    assert ir.count("@NRT_incref(") <= 1, ir.count("@NRT_incref(")
