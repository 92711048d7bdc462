"""Start-up cost of the CLI paths (issue 16): light imports, same numbers."""

import numpy as np
import pytest


@pytest.mark.parametrize("n", [1, 9, 10, 11, 97, 4096, 10001])
@pytest.mark.parametrize("cut", [0.0, 0.1, 0.25])
def test_trim_mean_equals_scipy(n, cut):
    from scipy.stats import trim_mean

    from mehs.synthesis.noise import _trim_mean

    a = np.round(np.random.default_rng(n).normal(3, 5, n))   # many ties, like rounded darks
    assert _trim_mean(a, cut) == pytest.approx(trim_mean(a, cut), rel=1e-12, abs=1e-12)


def test_chi2_quantiles_equal_scipy_stats():
    from scipy import stats
    from scipy.special import chdtri

    dof = np.arange(1, 800)
    np.testing.assert_allclose(chdtri(dof, 0.5), stats.chi2.median(dof), rtol=1e-12)
    np.testing.assert_allclose(chdtri(dof, 1e-4), stats.chi2.isf(1e-4, dof), rtol=1e-12)


def test_uncached_kernel_notice(tmp_path, capsys, monkeypatch):
    from types import SimpleNamespace

    from mehs.synthesis import _numba_cache
    from mehs.synthesis._numba_cache import notice_if_uncached

    monkeypatch.setattr(_numba_cache, "_told", False)

    idx = tmp_path / "k.nbi"
    cache_file = SimpleNamespace(_index_path=str(idx))
    disp = SimpleNamespace(_cache=SimpleNamespace(_cache_file=cache_file))
    assert notice_if_uncached(disp) is True
    assert "compiling the merge kernels once" in capsys.readouterr().err
    assert notice_if_uncached(disp) is False       # once per process
    monkeypatch.setattr(_numba_cache, "_told", False)
    idx.write_bytes(b"")
    assert notice_if_uncached(disp) is False
    assert notice_if_uncached(object()) is False
