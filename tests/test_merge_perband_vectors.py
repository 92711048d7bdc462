"""The per-band one-pass merge kernels stay vectorised on every Python numba runs on.

On Python 3.12 and 3.13 (numba 0.68) the censored residuals of the χ² statistic, read
under ``if cm != 0: for j …: if (cm >> j) & 1:``, left numba's reference counts of the
arrays read there unpruned: ``NRT_incref``/``NRT_decref`` calls inside the sample loop,
which LLVM does not vectorise. Every per-band kernel with the statistic ran scalar there,
8–11× its time on Python 3.11 (per-band Poisson 118 against 11 ms a 48-line chunk). The
residuals are now summed unconditionally, each behind a select (same bits).
"""

from __future__ import annotations

import pytest

from _checks import NO_VECTOR_BUILD as _NO_VECTOR_BUILD
from _checks import one_pass_division_counts


@pytest.mark.skipif(_NO_VECTOR_BUILD, reason="numba set to build without vectorisation "
                    "(NUMBA_CPU_NAME=generic, NUMBA_OPT=0 or NUMBA_BOUNDSCHECK)")
@pytest.mark.parametrize("name", ["poisson", "debevec"])
def test_the_per_band_kernels_with_the_statistic_are_vectorised(name):
    """Every division has a vector form in the kernel's code and no reference count is
    left in it (numba's own build, compiled afresh: numba shows no code of a cached
    kernel; 3 exposures, which LLVM's default tuning unrolls)."""
    from mehs.synthesis import _merge_fused, _merge_fused_weighted

    module = _merge_fused if name == "poisson" else _merge_fused_weighted
    vector, scalar, ir = one_pass_division_counts(getattr(module, f"merge_chunk_{name}_linear"),
                                                  weighted=name != "poisson", binned=False)
    assert scalar > 0 and vector >= scalar, (name, vector, scalar)
    # the arguments' own reference counts (once, at entry and exit) are all numba keeps
    assert ir.count("@NRT_incref(") <= 1, ir.count("@NRT_incref(")
