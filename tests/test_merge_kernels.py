"""The merge kernels' vectorisable pieces against their plain references (issue 16).

Debevec's hat weight and a linear sensor's ``g(z) = ln max(z, ½)`` are computed in
the kernel instead of looked up, and ``ln``/``exp`` are Cephes-style float32
versions; each fast path must give the table / libm path's numbers.
"""

from __future__ import annotations

import numpy as np
import pytest
from _checks import assert_same_merge_bits

from mehs.synthesis.merge import merge_bracket
from mehs.synthesis.response import ResponseCurve


def test_vectorised_exp_matches_numpy():
    from mehs.synthesis._merge_kernels import _exp_row

    x = np.concatenate([np.linspace(-80, 80, 200001), [0.0, -0.0, 1e-30, -1e-30]]).astype(np.float32)
    out = np.empty_like(x)
    _exp_row(x, out)
    ref = np.exp(x.astype(np.float64))
    assert np.max(np.abs(out - ref) / ref) < 2.5e-7           # ≤ 2 ulp of float32
    special = np.array([np.nan, 100.0, -100.0], np.float32)
    got = _exp_row(special, np.empty(3, np.float32))
    assert np.isnan(got[0]) and got[1] == np.inf and got[2] == 0.0


def test_vectorised_log_accumulation_matches_numpy():
    from mehs.synthesis._merge_kernels import _log_accumulate_row

    x = np.concatenate([np.arange(0.5, 4096, 0.5), np.geomspace(1e-30, 1e30, 5001)]).astype(np.float32)
    w = np.random.default_rng(0).uniform(0, 2, x.size).astype(np.float32)
    num = np.zeros(x.size, np.float32)
    den = np.zeros(x.size, np.float32)
    lt = np.float32(1.25)
    _log_accumulate_row(x, w, lt, num, den)
    ref = w.astype(np.float64) * (np.log(x.astype(np.float64)) - 1.25)
    np.testing.assert_allclose(num, ref, rtol=3e-6, atol=1e-5)
    np.testing.assert_array_equal(den, w)


def test_scalar_cephes_forms_match_numpy_over_the_float_range():
    """The scalar ``logf`` / ``expf`` (bit views through LLVM bitcasts) that both the
    one-pass kernels and the row forms use: within 2 ulp of float64 numpy from the
    smallest normal to the largest float, and on the special values."""
    from numba import njit

    from mehs.synthesis._cephes import expf, logf

    @njit
    def logs(x, o):
        for i in range(x.shape[0]):
            o[i] = logf(x[i])

    @njit
    def exps(x, o):
        for i in range(x.shape[0]):
            o[i] = expf(x[i])

    rng = np.random.default_rng(0)
    x = np.concatenate([np.float32(2) ** rng.uniform(-125, 127, 20001).astype(np.float32),
                        np.arange(0.5, 4096, 0.5)]).astype(np.float32)
    got = np.empty_like(x)
    logs(x, got)
    ref = np.log(x.astype(np.float64))
    big = np.abs(ref) > 1e-3
    assert np.max(np.abs(got[big] - ref[big]) / np.abs(ref[big])) < 2.5e-7
    y = np.concatenate([np.linspace(-90, 90, 20001),
                        [np.nan, np.inf, -200.0, 0.0, -0.0, 1e-30]]).astype(np.float32)
    got = np.empty_like(y)
    exps(y, got)
    fin = np.abs(y) < 80
    ref = np.exp(y[fin].astype(np.float64))
    assert np.max(np.abs(got[fin] - ref) / ref) < 2.5e-7
    assert np.isnan(got[-6]) and got[-5] == np.inf and got[-4] == 0.0


def _bracket(seed=3):
    rng = np.random.default_rng(seed)
    E = np.exp(rng.uniform(np.log(0.2), np.log(2000), (12, 33, 9))).astype(np.float32)
    t = [1.0, 4.0, 16.0]
    stack = [np.clip(np.rint(E * tj + 50 + rng.normal(0, 3, E.shape)), 0, 4095).astype(np.uint16)
             for tj in t]
    return stack, t, [np.full((33, 9), 50.0)] * 3


@pytest.mark.parametrize("method", ["debevec", "robertson"])
def test_computed_hat_weight_equals_the_table_lookup(method):
    """A weighting equal to the hat up to a constant factor takes the table path; a
    constant factor cancels in both estimators, so the two paths must agree."""
    from mehs.synthesis.response import weight_hat

    stack, t, darks = _bracket()
    fast = merge_bracket(stack, t, method=method, darks=darks)
    table = merge_bracket(stack, t, method=method, darks=darks,
                          weighting=lambda z: weight_hat(z.size) * 0.75)
    np.testing.assert_allclose(np.asarray(fast.radiance), np.asarray(table.radiance),
                               rtol=2e-6, atol=1e-6)


def test_computed_linear_curve_equals_the_table_lookup():
    """``ln max(z, ½)`` computed vs looked up in a table shifted by 1e-6 (so not recognised
    as the linear curve): the radiances agree to that shift."""
    stack, t, darks = _bracket()
    g = np.log(np.maximum(np.arange(4096, dtype=np.float64), 0.5)) + 1e-6
    shifted = ResponseCurve(g, 12, method="linear", weighting="hat")
    assert not np.all(shifted.table().astype(np.float32)
                      == ResponseCurve.linear(12).table().astype(np.float32))
    fast = merge_bracket(stack, t, method="debevec", darks=darks)
    table = merge_bracket(stack, t, method="debevec", darks=darks, response=shifted)
    np.testing.assert_allclose(np.asarray(table.radiance), np.asarray(fast.radiance),
                               rtol=4e-6, atol=1e-6)


def _stress_bracket(seed, P, nl=9, ns=37, nb=11):
    """Raws with censored samples (a bright object in the longest exposure), a pixel
    saturated in every exposure, negative dark-subtracted values, a missing dark."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(1, 40, P))
    t[0] = 1.0
    E = (np.exp(rng.uniform(np.log(0.05), np.log(6000), (nl, ns, 1)))
         * rng.uniform(0.2, 1, (1, 1, nb)))
    stack = []
    for j in range(P):
        x = E * t[j] + 60 + rng.normal(0, 4, E.shape)
        if j == P - 1:
            x[:3, :5] += 5000
        x[4, 7] = 5000
        stack.append(np.clip(np.rint(x), 0, 4095).astype(np.uint16))
    darks = [np.full((ns, nb), 60.0) + rng.normal(0, 1, (ns, nb)) for _ in range(P)]
    if seed % 3 == 0:
        darks[1] = None
    return stack, t, darks


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("P", [2, 3, 4])
@pytest.mark.parametrize("consistency", [True, False])
@pytest.mark.parametrize("clip", [True, False])
def test_one_pass_poisson_kernel_equals_the_stage_kernel_to_the_bit(seed, P, consistency, clip,
                                                                      monkeypatch):
    """The default merge of a linear sensor (one pass per sample) gives the stage kernel's
    numbers exactly: estimate, fallback, SNR, mask, χ² with censored residuals, dof."""
    from mehs.synthesis import _merge_fused
    from mehs.synthesis._merge_kernels import merge_chunk_poisson
    from mehs.synthesis.merge import NoiseModel, merge_bracket

    stack, t, darks = _stress_bracket(seed, P)
    # (per band: the stage kernel has no binned statistic)
    kw = dict(darks=darks, bit_depth=12, consistency=consistency, clip_negative=clip,
              noise=NoiseModel(1.7, 3.0, relative=0.01 if seed % 2 else 0.0),
              calibration=np.linspace(0.5, 2, stack[0].shape[2]), consistency_bins=1)
    fused = merge_bracket(stack, t, **kw)

    def stage(zs, darks, sat, times, gain, avar, rel_var, cal, want_chi2, clip, *outs):
        merge_chunk_poisson(zs, darks, sat, times, True, False, np.zeros((1, 2), np.float32),
                            4096, gain, avar, rel_var, cal, want_chi2, clip, *outs)

    monkeypatch.setattr(_merge_fused, "merge_chunk_poisson_linear", stage)
    monkeypatch.setattr(_merge_fused, "merge_chunk_poisson_linear_radiance", stage)
    ref = merge_bracket(stack, t, **kw)
    if consistency:
        assert ref.dof.max() > 0 and (ref.mask & 1).any()       # the rare paths were taken
    assert_same_merge_bits(fused, ref)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("P", [2, 3, 4])
@pytest.mark.parametrize("method", ["debevec", "robertson", "inverse-variance"])
@pytest.mark.parametrize("consistency,clip", [(True, True), (False, False)])
def test_one_pass_weighted_kernel_equals_the_stage_kernel_to_the_bit(seed, P, method,
                                                                       consistency, clip,
                                                                       monkeypatch):
    """Debevec / Robertson / inverse-variance of a linear sensor in one pass per sample
    (scalar Cephes ln/exp) give the stage kernel's numbers exactly, rare paths included."""
    from mehs.synthesis import _merge_fused_weighted
    from mehs.synthesis._merge_kernels import merge_chunk
    from mehs.synthesis._merge_rows import DEBEVEC, INVVAR, ROBERTSON
    from mehs.synthesis.merge import NoiseModel
    from mehs.synthesis.response import weighting_table

    stack, t, darks = _stress_bracket(seed, P)
    kw = dict(method=method, darks=darks, bit_depth=12, consistency=consistency,
              clip_negative=clip, noise=NoiseModel(1.7, 3.0, relative=0.01 if seed % 2 else 0.0),
              calibration=np.linspace(0.5, 2, stack[0].shape[2]))
    fused = merge_bracket(stack, t, **kw)
    seen = []
    glut = ResponseCurve.linear(12).table().astype(np.float32)
    wlut = weighting_table("hat", 4096).astype(np.float32)

    code = {"debevec": DEBEVEC, "robertson": ROBERTSON, "inverse-variance": INVVAR}[method]

    def stage(zs, darks, sat, times, L, floor, gain, avar, rel_var, cal, want_chi2, clip, *outs):
        seen.append(code)
        merge_chunk(zs, darks, sat, times, True, False, glut, np.exp(glut), wlut, True, True,
                    floor, gain, avar, rel_var, cal, code, want_chi2, clip, *outs)

    name = {"debevec": "debevec", "robertson": "robertson", "inverse-variance": "invvar"}[method]
    monkeypatch.setattr(_merge_fused_weighted, f"merge_chunk_{name}_linear", stage)
    monkeypatch.setattr(_merge_fused_weighted, f"merge_chunk_{name}_linear_radiance", stage)
    ref = merge_bracket(stack, t, **kw)
    assert seen                                                # the one-pass kernel was used
    if consistency:
        assert ref.dof.max() > 0 and (ref.mask & 1).any()       # the rare paths were taken
    assert_same_merge_bits(fused, ref)


def test_the_merge_runs_the_radiance_only_kernel_without_the_statistic(monkeypatch):
    """``consistency=False`` runs each one-pass method's ``*_radiance`` kernel (the statistic
    off at compile time), ``True`` the statistic's; ``fuse`` warms the one it will run."""
    from mehs.cube import SpectralCube
    from mehs.synthesis import fuse as fuse_mod
    from mehs.synthesis import merge as merge_mod
    from mehs.synthesis.bracket import Bracket

    kinds = []
    real = merge_mod._numba_kernel
    monkeypatch.setattr(merge_mod, "_numba_kernel",
                        lambda kind, code: kinds.append(kind) or real(kind, code))
    stack, t, darks = _stress_bracket(0, 3)
    for method in ("poisson", "debevec", "robertson", "inverse-variance"):
        for consistency in (True, False):
            r = merge_mod.merge_bracket(stack, t, method=method, darks=darks,
                                        consistency=consistency)
            assert (r.dof.max() > 0) == consistency
    assert kinds == [k + v for k in ("poisson_linear", "debevec_linear", "robertson_linear",
                                     "invvar_linear") for v in ("", "_radiance")]
    warmed = []
    monkeypatch.setattr(fuse_mod, "warm_merge_kernel",
                        lambda *a, **kw: warmed.append(kw.get("consistency")))
    monkeypatch.setattr(fuse_mod, "merge_bracket", lambda *a, **kw: (_ for _ in ()).throw(
        RuntimeError(f"merge consistency={kw['consistency']}")))
    wl = np.linspace(400, 1000, stack[0].shape[2])
    br = Bracket([SpectralCube(s, wl) for s in stack],
                 [d if d is None else d.astype(np.float32) for d in darks], [None] * 3,
                 list(t), wl, bit_depth=12)
    for ghosts, want in (("detect", True), ("off", False)):
        with pytest.raises(RuntimeError, match=f"consistency={want}"):
            fuse_mod.fuse_bracket(br, response="linear", ghosts=ghosts)
    assert warmed == [True, False]


def test_a_bit_depth_that_contradicts_the_curve_is_refused():
    """12-bit raws with a 16-bit curve merged with 0.98·65535 as saturation and clipped
    samples as valid (a 3000 DN/ms pixel came out 533): now an InputError; without
    ``bit_depth`` the curve's depth is used."""
    from mehs.errors import InputError
    from mehs.synthesis.merge import merge_bracket

    stack, t, darks = _stress_bracket(0, 3)
    with pytest.raises(InputError, match="16-bit"):
        merge_bracket(stack, t, darks=darks, bit_depth=12, response=ResponseCurve.linear(16))
    a = merge_bracket(stack, t, darks=darks, response=ResponseCurve.linear(12))
    b = merge_bracket(stack, t, darks=darks, bit_depth=12)
    np.testing.assert_array_equal(np.asarray(a.radiance), np.asarray(b.radiance))


def test_float_raws_through_a_raw_level_curve_round_to_the_nearest_level():
    """Dark subtracted after linearisation (a curve recovered on raw levels): a float raw
    DN is the nearest level, not the one below (truncation biased the radiance by −0.9 %,
    −2 % at low signal); with the curve ``ln z`` the merge equals the linear one to the
    rounding."""
    from mehs.synthesis.fuse import _lineariser
    from mehs.synthesis.merge import merge_bracket

    rng = np.random.default_rng(0)
    E = np.exp(rng.uniform(np.log(2), np.log(100), (16, 16, 4)))
    t = np.array([1.0, 4.0, 16.0])
    dark = np.full((16, 4), 40.0, np.float32)
    stack = [(E * tt + 40.0).astype(np.float32) for tt in t]
    g = np.log(np.maximum(np.arange(4096.0), 0.5))
    curve = ResponseCurve(g, 12, method="debevec1997", parameters={"levels": "raw"})
    r = merge_bracket(stack, t, response=curve, darks=[dark] * 3, consistency=False)
    assert r.info["dark_mode"] == "linear"
    rel = np.asarray(r.radiance) / E - 1
    assert abs(rel.mean()) < 2e-3
    lin = _lineariser(curve, "linear", 12, [True] * 3)
    np.testing.assert_allclose(lin(np.array([[52.7, 52.2]]), np.array([[40.0, 40.0]]), 0),
                               [[13.0, 12.0]], rtol=1e-12)


def test_per_band_curves_convert_each_bands_darks_for_the_noise_model():
    """With per-band curves the noise model's dark current came from band 0's curve for
    every band: swapping two bands' curves (identical darks in both) moved it 5 → 20 DN/ms.
    Each band's darks now go through its own curve, so the swap changes nothing."""
    import warnings

    from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket
    from mehs.cube import SpectralCube
    from mehs.synthesis.bracket import Bracket
    from mehs.synthesis.fuse import estimate_noise

    wl = SPECIM_IQ_WAVELENGTHS[[60, 61]]
    sc = make_scene("colorchecker", lines=48, samples=48, wavelengths=wl, source_ratio=0, seed=1)
    sen = SensorModel(response="gamma", seed=2, radiance_to_e_per_ms=1600.0,
                      dark_current_e_per_ms=20.0)
    sim = simulate_bracket(sc, sen, [4.0, 16.0, 64.0], seed=3)
    dk = [np.repeat(d[:, :1], 2, axis=1) for d in sim.darks]
    br = Bracket([SpectralCube(e, wl) for e in sim.exposures], dk, [None] * 3, sim.times_ms, wl,
                 bit_depth=12)
    g = sen.true_log_inverse_response(np.arange(4096))
    sat = np.full(2, 0.98 * 4095, np.float32)
    dcs = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for G in (np.stack([g, g + np.log(4)]), np.stack([g + np.log(4), g])):
            c = ResponseCurve(G, 12, method="debevec1997", parameters={"levels": "raw"})
            dcs.append(estimate_noise(br, c, sat)[0].dark_current)
    assert dcs[0] == pytest.approx(dcs[1], rel=1e-6)
