"""The χ² ghost statistic of binned bands (``merge_bracket(consistency_bins=k)``, issue 16).

Checked against the per-band kernel (one band per bin: every number to the bit), against
a numpy statistic written from the formula (bins with and without a censored exposure, a
short last bin), against the simulator's moving scenes (it flags more of the moving
pixels than the per-band statistic, no static one) and through the stored entry point.
"""

import numpy as np
import pytest

from _checks import assert_same_merge_bits
from mehs.errors import InputError
from mehs.synthesis.merge import NoiseModel, merge_bracket
from test_merge_kernels import _stress_bracket

NOISE = NoiseModel(1.7, 3.0)


@pytest.mark.parametrize("seed,P", [(s, P) for s in range(3) for P in (2, 3, 4)] + [(1, 16)])
def test_bins_of_one_band_give_the_per_band_kernels_numbers_to_the_bit(seed, P, monkeypatch):
    """Censored, saturated-in-all and negative samples included (the stress bracket)."""
    from mehs.synthesis import _merge_binned, _merge_fused

    stack, t, darks = _stress_bracket(seed, P)
    kw = dict(darks=darks, bit_depth=12, clip_negative=bool(seed % 2),
              noise=NoiseModel(1.7, 3.0, relative=0.01 if seed % 2 else 0.0),
              calibration=np.linspace(0.5, 2, stack[0].shape[2]), consistency_bins=1)
    per_band = merge_bracket(stack, t, **kw)
    ns = stack[0].shape[1]

    def binned_one(zs, darks, sat, times, gain, avar, rel_var, cal, want_chi2, clip, *outs):
        scratch = (tuple(np.empty(ns, np.float32) for _ in zs), np.empty(ns, np.float32),
                   np.empty(ns, np.int32))
        _merge_binned.merge_chunk_poisson_linear_binned(
            zs, darks, sat, times, gain, avar, rel_var, cal, want_chi2, clip, 1, *scratch, *outs)

    monkeypatch.setattr(_merge_fused, "merge_chunk_poisson_linear", binned_one)
    ref = merge_bracket(stack, t, **kw)
    assert per_band.dof.max() > 0 and (per_band.mask & 1).any()
    assert_same_merge_bits(ref, per_band)


def _statistic(y, used, cens_level, t, nbin, noise):
    """The binned χ² and dof per pixel from the formula, float64.

    ``y`` (P, lines, samples, bands) dark-subtracted levels; ``used`` the merge's choice
    per band; ``cens_level`` the censored samples' dark-subtracted saturation level (NaN
    where not censored)."""
    P, nl, ns, nb = y.shape
    tt = np.asarray(t, np.float64)[:, None, None]
    avar = noise.zero_signal_variance(t)[:, None, None]
    n_used = used.sum(0)
    xi = np.where(n_used > 0, (used * y).sum(0) / np.maximum((used * tt[..., None]).sum(0), 1e-300),
                  y[0] / t[0])
    chi2 = np.zeros((nl, ns))
    dof = np.zeros((nl, ns), int)
    for a0 in range(0, nb, nbin):
        sl = slice(a0, min(a0 + nbin, nb))
        kb = sl.stop - sl.start
        xp = np.maximum(xi[..., sl], 0).sum(-1)
        u = used[..., sl].all(-1)
        censored = np.isfinite(cens_level[..., sl])
        cov = (used[..., sl] | censored).all(-1)
        cb = cov & ~u & censored.any(-1)
        level = np.where(used[..., sl], y[..., sl], np.nan_to_num(cens_level[..., sl])).sum(-1)
        x = level / tt
        w = 1.0 / ((noise.gain * xp * tt + kb * avar) / tt ** 2 + noise.relative ** 2 * xp ** 2)
        sw = (u * w).sum(0)
        mean = np.where(sw > 0, (u * w * x).sum(0) / np.where(sw > 0, sw, 1), 0)
        q = (u * w * (x - mean) ** 2).sum(0)
        r = x - mean
        q = q + (cb * w * np.where(r > 0, r, 0) ** 2).sum(0)
        nv, nc = u.sum(0), cb.sum(0)
        ok = (nv + nc >= 2) & (nv > 0)
        chi2 += np.where(ok, q, 0)
        dof += np.where(ok, nv + nc - 1, 0)
    return chi2, dof


def test_binned_statistic_is_the_formulas_with_a_short_last_bin():
    """Every exposure used (levels far from saturation): bins of 4 over 11 bands (4, 4, 3)."""
    rng = np.random.default_rng(4)
    t = [1.0, 4.0, 16.0]
    E = np.exp(rng.uniform(np.log(2.0), np.log(100.0), (7, 13, 11)))
    E[2:4, 3:6] *= np.linspace(0.6, 1.4, 11)      # a spectrum that changes between exposures:
    stack, ys = [], []
    for j, tj in enumerate(t):
        e = E * (1.0 + 0.3 * j * (np.arange(7)[:, None, None] == 2)) * tj
        raw = np.clip(np.rint(e + 60 + rng.normal(0, 3, E.shape)), 0, 4095)
        stack.append(raw.astype(np.uint16))
        ys.append(raw - 60.0)
    r = merge_bracket(stack, t, darks=[np.full((13, 11), 60.0)] * 3, noise=NOISE,
                      consistency_bins=4)
    y = np.stack(ys)
    chi2, dof = _statistic(y, np.ones(y.shape, bool), np.full(y.shape, np.nan), t, 4, NOISE)
    np.testing.assert_array_equal(r.dof, dof)
    assert (dof == 3 * 2).all()
    # (float32's Σwx² − (Σwx)²/Σw, as the per-band kernel's: ~1e-3 of a χ² near 1 here)
    np.testing.assert_allclose(r.chi2, chi2, rtol=1e-3, atol=3e-3)
    assert r.info["consistency_bins"] == 4
    assert chi2[2].mean() > 10 * chi2[[0, 1, 3, 4, 5, 6]].mean()     # the changed line


def test_a_bin_with_a_censored_band_adds_the_censored_residual():
    """The longest exposure saturates in two bands of the first bin where the shorter
    ones predict it far below saturation (a bright object moved in): the bin keeps that
    exposure as censored, its bound the two used bands' levels and the two saturation
    levels."""
    t = [1.0, 4.0, 16.0]
    nl, ns, nb = 2, 3, 8
    E = np.full((nl, ns, nb), 20.0)
    stack = [np.rint(E * tj + 60).astype(np.uint16) for tj in t]
    stack[2][0, 1, 1:3] = 4095                    # censored in bands 1 and 2
    stack[2][1, 2, 5] = 4095                      # and once in the second bin
    sat = 0.98 * 4095
    r = merge_bracket(stack, t, darks=[np.full((ns, nb), 60.0)] * 3, noise=NOISE,
                      saturation=sat, consistency_bins=4)
    y = np.stack([s.astype(float) - 60.0 for s in stack])
    used = np.stack([s < np.float32(sat) for s in stack])
    cens = np.where(~used, np.float32(sat) - 60.0, np.nan)
    chi2, dof = _statistic(y, used, cens, t, 4, NOISE)
    np.testing.assert_array_equal(r.dof, dof)
    assert dof[0, 1] == 2 * 2 and dof[1, 2] == 2 * 2          # 2 used + 1 censored, 2 bins
    np.testing.assert_allclose(r.chi2, chi2, rtol=2e-4, atol=1e-3)
    assert r.chi2[0, 1] > 1e3 and r.chi2[1, 2] > 1e3
    assert r.chi2[0, 0] < 50


def test_binned_bins_flag_more_of_a_dim_moving_patch_and_no_static_pixel():
    """The simulator's moving patch at a tenth of its brightness: the test alone (each
    pixel's χ² against its threshold) flags more of the moving pixels with bins of 4 than
    per band, and nothing away from them."""
    from scipy.ndimage import binary_dilation

    from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket
    from mehs.synthesis.ghost import detect_ghosts

    sc = make_scene("colorchecker", lines=48, samples=48, wavelengths=SPECIM_IQ_WAVELENGTHS,
                    seed=2, motion=True)
    spec = sc._blob_spectrum
    sc.radiance = np.maximum(sc.radiance - np.float32(0.9) * sc._blob(0)[..., None]
                             * spec[None, None, :], 0.0)
    sc._blob_spectrum = spec * np.float32(0.1)
    times = [0.5, 2.0, 8.0]
    sim = simulate_bracket(sc, SensorModel(seed=2), times, seed=2)
    truth = sc.moved_between(range(3))
    far = ~binary_dilation(truth, iterations=2)
    flagged = {}
    for k in (1, 4):
        r = merge_bracket(list(sim.exposures), sim.times_ms, darks=list(sim.darks),
                          bit_depth=12, consistency_bins=k)
        flagged[k] = detect_ghosts(r.chi2, r.dof, min_pixels=1, grow=0).mask
        assert not (flagged[k] & far).any()
    assert truth.sum() > 50
    assert flagged[4][truth].sum() > 1.2 * flagged[1][truth].sum()


def test_bins_other_than_one_are_refused_where_not_implemented_and_when_not_whole():
    stack, t, darks = _stress_bracket(0, 3)
    for bad in (0, -2, 2.5, True, "4.0", "four"):   # ("4", as a command line gives it: 4)
        with pytest.raises(InputError, match="consistency_bins"):
            merge_bracket(stack, t, darks=darks, consistency_bins=bad)
    with pytest.raises(InputError, match="merges of a linear sensor"):
        merge_bracket(stack, t, darks=darks, method="debevec", weighting="uniform",
                      consistency_bins=4)
    # 17 exposures: more than the kernel's masks hold (review: the 17th was taken for censored)
    s17, t17, d17 = _stress_bracket(0, 17, nb=4)
    with pytest.raises(InputError, match="at most 16 exposures"):
        merge_bracket(s17, t17, darks=d17, consistency_bins=2)
    wide = [np.repeat(s, 25, axis=2) for s in s17]
    r = merge_bracket(wide, t17, darks=[None] * 17)
    assert r.info["consistency_bins"] == 1
    # without the statistic the bins change nothing
    a = merge_bracket(stack, t, darks=darks, consistency=False, consistency_bins=4,
                      method="debevec")
    b = merge_bracket(stack, t, darks=darks, consistency=False, method="debevec")
    assert_same_merge_bits(a, b)


def test_the_stored_binned_kernel_gives_the_numba_kernels_bits(tmp_path, monkeypatch):
    from mehs.synthesis import _native

    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path / "cache"))
    stack, t, darks = _stress_bracket(1, 3)
    kw = dict(darks=darks, noise=NoiseModel(1.5, 3.0, relative=0.01), consistency_bins=3)
    stored = merge_bracket(stack, t, **kw)
    assert _native.is_stored("poisson_linear_binned", np.uint16, 3)
    monkeypatch.setenv("MEHS_CACHE_DIR", "")
    ref = merge_bracket(stack, t, **kw)
    assert ref.dof.max() > 0
    assert_same_merge_bits(stored, ref)


def test_auto_bins_a_dense_spectrum_of_a_linear_merge_only():
    """Bins of 4 for the merges of a linear sensor's cube of ≥ 100 bands; one band per bin
    for a few broad bands (a change may flip its sign between them) and for the merges
    without a binned kernel (another weighting than the hat)."""
    from mehs.synthesis.merge import AUTO_BINS_MIN_BANDS, AUTO_CONSISTENCY_BINS

    rng = np.random.default_rng(0)
    t = [1.0, 4.0, 16.0]
    for nb, want in ((AUTO_BINS_MIN_BANDS, AUTO_CONSISTENCY_BINS), (AUTO_BINS_MIN_BANDS - 1, 1)):
        E = rng.uniform(5, 50, (3, 4, nb))
        stack = [np.rint(E * tj + 60 + rng.normal(0, 2, E.shape)).astype(np.uint16) for tj in t]
        darks = [np.full((4, nb), 60.0)] * 3
        r = merge_bracket(stack, t, darks=darks, noise=NOISE)
        assert r.info["consistency_bins"] == want
        assert (r.dof == -(-nb // want) * 2).all()
        assert merge_bracket(stack, t, darks=darks, noise=NOISE, method="robertson",
                             weighting="gaussian").info["consistency_bins"] == 1
        assert merge_bracket(stack, t, darks=darks, consistency=False).info[
            "consistency_bins"] is None
