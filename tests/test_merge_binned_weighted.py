"""The weighted merges' χ² ghost statistic of binned bands (issue 16): Debevec, Robertson and
inverse variance with ``merge_bracket(consistency_bins=k)``.

The oracle is two merges tested elsewhere. The radiance, confidence, mask and band means
are the weighted merge's with one band per bin, to the bit: the bins change only the
statistic. Its χ² and degrees of freedom are the Poisson merge's with the same bins, to
the bit: the weighted merges test consistency about the pooled (Poisson) estimate over the
same choice of samples, and the Poisson binned statistic is checked against a numpy
statistic written from the formula in ``test_merge_binned``.
"""

import numpy as np
import pytest

from _checks import NO_VECTOR_BUILD as _NO_VECTOR_BUILD
from _checks import assert_same_merge_bits, one_pass_division_counts
from mehs.errors import InputError
from mehs.synthesis.merge import (AUTO_BINS_MAX_EXPOSURES, AUTO_BINS_MIN_BANDS,
                                  AUTO_CONSISTENCY_BINS, NoiseModel, merge_bracket)
from mehs.synthesis.merge_types import BINNED_MAX_EXPOSURES
from test_merge_kernels import _stress_bracket

METHODS = ("debevec", "robertson", "inverse-variance")


def _same(a, b, what):
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    assert a.dtype == b.dtype, what
    np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8), err_msg=what)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("seed,nbin", [(0, 4), (1, 3), (2, 11)])
def test_binned_weighted_merge_is_the_weighted_radiance_with_the_poisson_binned_statistic(
        method, seed, nbin):
    """Censored, saturated-in-all and negative samples (the stress bracket, 11 bands: a
    short last bin for 4 and 3, one bin of every band for 11)."""
    stack, t, darks = _stress_bracket(seed, 3)
    nb = stack[0].shape[2]
    kw = dict(darks=darks, bit_depth=12, clip_negative=bool(seed % 2),
              noise=NoiseModel(1.7, 3.0, relative=0.01 if seed % 2 else 0.0),
              calibration=np.linspace(0.5, 2, nb))
    got = merge_bracket(stack, t, method=method, consistency_bins=nbin, **kw)
    per_band = merge_bracket(stack, t, method=method, consistency_bins=1, **kw)
    poisson = merge_bracket(stack, t, method="poisson", consistency_bins=nbin, **kw)
    assert got.info["consistency_bins"] == nbin == poisson.info["consistency_bins"]
    for k in ("radiance", "confidence", "mask", "mean_radiance"):
        _same(getattr(got, k), getattr(per_band, k), k)
    _same(got.info["nvalid"], per_band.info["nvalid"], "nvalid")
    for k in ("chi2", "dof"):
        _same(getattr(got, k), getattr(poisson, k), k)
    # a statistic of bins, not of bands: fewer degrees of freedom, and inconsistencies seen
    assert got.dof.max() > 0 and (got.chi2 > 0).any()
    assert got.dof.sum() < per_band.dof.sum()
    # the weighted radiance, not the Poisson one
    assert not np.array_equal(got.radiance, poisson.radiance)


def test_bins_are_refused_where_the_merge_has_no_binned_kernel():
    from mehs.synthesis.response import ResponseCurve

    stack, t, darks = _stress_bracket(0, 3)
    with pytest.raises(InputError, match="consistency_bins=4 .* not the 'gaussian' weighting"):
        merge_bracket(stack, t, darks=darks, method="robertson", weighting="gaussian",
                      consistency_bins=4)
    bent = ResponseCurve(np.log(np.maximum(np.arange(4096.0), 0.5)) * 1.01, 12, "debevec")
    for method in ("poisson", "debevec"):
        with pytest.raises(InputError, match="not a recovered response curve; use "
                                             "consistency_bins=1"):
            merge_bracket(stack, t, darks=darks, method=method, response=bent,
                          consistency_bins=2)
        # auto: one band per bin there, no error
        assert merge_bracket(stack, t, darks=darks, method=method, response=bent).info[
            "consistency_bins"] == 1


@pytest.mark.parametrize("method", ["robertson", "inverse-variance"])
def test_auto_bins_a_dense_spectrum_of_every_linear_merge(method):
    rng = np.random.default_rng(0)
    t = [1.0, 4.0, 16.0]
    noise = NoiseModel(1.7, 3.0)
    for nb, want in ((AUTO_BINS_MIN_BANDS, AUTO_CONSISTENCY_BINS), (AUTO_BINS_MIN_BANDS - 1, 1)):
        E = rng.uniform(5, 50, (3, 4, nb))
        stack = [np.rint(E * tj + 60 + rng.normal(0, 2, E.shape)).astype(np.uint16) for tj in t]
        darks = [np.full((4, nb), 60.0)] * 3
        r = merge_bracket(stack, t, darks=darks, noise=noise, method=method)
        assert r.info["consistency_bins"] == want
        assert (r.dof == -(-nb // want) * 2).all()
        # another weighting has no binned kernel: auto takes one band per bin
        assert merge_bracket(stack, t, darks=darks, noise=noise, method=method,
                             weighting="uniform").info["consistency_bins"] == 1


def test_the_stored_weighted_binned_kernel_gives_the_numba_kernels_bits(tmp_path, monkeypatch):
    from mehs.synthesis import _native

    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path / "cache"))
    stack, t, darks = _stress_bracket(1, 3)
    kw = dict(darks=darks, noise=NoiseModel(1.5, 3.0, relative=0.01), consistency_bins=3,
              method="debevec")
    stored = merge_bracket(stack, t, **kw)
    assert _native.is_stored("debevec_linear_binned", np.uint16, 3)
    monkeypatch.setenv("MEHS_CACHE_DIR", "")
    ref = merge_bracket(stack, t, **kw)
    assert ref.dof.max() > 0
    assert_same_merge_bits(stored, ref)


@pytest.mark.skipif(_NO_VECTOR_BUILD, reason="numba set to build without vectorisation "
                    "(NUMBA_CPU_NAME=generic, NUMBA_OPT=0 or NUMBA_BOUNDSCHECK)")
@pytest.mark.parametrize("name", ["debevec", "robertson", "invvar", "poisson"])
def test_llvm_vectorises_the_binned_kernels_with_its_default_tuning(name):
    """Every division of a binned kernel has a vector form in its machine code (a scalar
    ``fdiv`` remains per division for the loop's remainder), in numba's own build for the
    exposures LLVM's default tuning unrolls (:data:`DEFAULT_TUNED_EXPOSURES`; beyond, the
    stored kernels are compiled with other LLVM options: tests/test_native_exposures.py).
    Reviews of session 35: the weighted estimate through an inline helper returning a
    tuple kept Debevec's and Robertson's sample loops scalar in numba's own (256-bit)
    build: 9× the per-band time, to the same bits. Compiled afresh (numba shows no code of
    a cached kernel)."""
    from mehs.synthesis import _merge_binned, _merge_binned_weighted

    module = _merge_binned if name == "poisson" else _merge_binned_weighted
    vector, scalar, _ = one_pass_division_counts(
        getattr(module, f"merge_chunk_{name}_linear_binned"), weighted=name != "poisson",
        binned=True)
    assert scalar > 0 and vector >= scalar, (name, vector, scalar)


def test_auto_bins_the_brackets_the_binned_kernels_take():
    """Auto bins brackets of up to :data:`AUTO_BINS_MAX_EXPOSURES` (the binned kernels'
    limit, their stored kernels vectorised for all of them; session 35 had held it to 3)
    and keeps the per-band statistic beyond, where a width asked for is refused."""
    assert AUTO_BINS_MAX_EXPOSURES == BINNED_MAX_EXPOSURES == 16
    rng = np.random.default_rng(1)
    nb = AUTO_BINS_MIN_BANDS
    for P, want, methods in ((5, AUTO_CONSISTENCY_BINS, ("poisson", "robertson")),
                             (AUTO_BINS_MAX_EXPOSURES + 1, 1, ("poisson",))):
        t = [2.0 ** j for j in range(P)]
        E = rng.uniform(0.5, 3, (2, 3, nb))
        stack = [np.clip(np.rint(E * tj + 60 + rng.normal(0, 2, E.shape)), 0, 4095)
                 .astype(np.uint16) for tj in t]
        kw = dict(darks=[np.full((3, nb), 60.0)] * P, noise=NoiseModel(1.7, 3.0))
        for method in methods:
            r = merge_bracket(stack, t, method=method, **kw)
            assert r.info["consistency_bins"] == want, (P, method)
    with pytest.raises(InputError, match="at most 16 exposures"):
        merge_bracket(stack, t, consistency_bins=4, **kw)
