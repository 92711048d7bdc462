"""numpy's BLAS is pinned to one thread inside the hot paths and restored after (issue 16)."""

import numpy as np
import pytest

threadpoolctl = pytest.importorskip("threadpoolctl")

from mehs._blas import single_thread_blas  # noqa: E402


def _blas_threads():
    return [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]


def test_single_thread_blas_limits_and_restores():
    before = _blas_threads()
    if not before:
        pytest.skip("no BLAS library visible to threadpoolctl")
    with single_thread_blas():
        assert _blas_threads() == [1] * len(before)
    assert _blas_threads() == before


def test_pinned_products_give_the_same_numbers():
    # the pinning changes the thread count only, never the result
    from mehs.ssr.baselines import RGB_to_spectra_Smits1999, smits_coefficients, smits_basis

    rgb = np.random.default_rng(0).gamma(1.0, 1.0, (64, 48, 3)).astype(np.float64)
    ref = smits_coefficients(rgb) @ smits_basis()
    np.testing.assert_allclose(RGB_to_spectra_Smits1999(rgb), ref, rtol=1e-12, atol=1e-12)
