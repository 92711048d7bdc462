"""Luminance restoration, Reinhard pre-processing and the pipeline switches."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from mehs.rgb import WAVELENGTHS_31, XYZ_TO_SRGB, cmfs_matrix, linear_sRGB_to_XYZ, spectra_to_XYZ
from mehs.ssr.luminance import restore_luminance
from mehs.ssr.metrics import sam_deg
from mehs.ssr.models import FunctionModel
from mehs.ssr.pipeline import predict
from mehs.ssr.preprocess import inverse_reinhard, reinhard

W = WAVELENGTHS_31


def xyz_sum_spectra(s):
    return spectra_to_XYZ(np.asarray(s, dtype=np.float64), W).sum(-1)


def xyz_sum_rgb(rgb):
    return linear_sRGB_to_XYZ(np.asarray(rgb, dtype=np.float64)).sum(-1)


spectra_st = hnp.arrays(np.float32, (3, 4, 31),
                        elements=st.one_of(st.just(0.0), st.floats(0, 1e4, width=32)))
rgb_st = hnp.arrays(np.float32, (3, 4, 3), elements=st.floats(0, 1e4, width=32))


@settings(max_examples=60, deadline=None)
@given(S=spectra_st, rgb=rgb_st)
def test_restored_cube_has_input_xyz_sum(S, rgb):
    out = restore_luminance(S, rgb, W)
    assert out.dtype == np.float32 and out.shape == S.shape
    assert np.all(np.isfinite(out))
    want = xyz_sum_rgb(rgb)
    got = xyz_sum_spectra(out)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-30)


@settings(max_examples=40, deadline=None)
@given(S=hnp.arrays(np.float64, (5, 31), elements=st.floats(-1e3, 1e3)),
       rgb=hnp.arrays(np.float64, (5, 3), elements=st.floats(0, 1e3)))
def test_any_real_spectra_get_the_input_xyz_sum(S, rgb):
    out = restore_luminance(S, rgb, W)
    assert np.all(np.isfinite(out))
    scale = np.abs(out) @ np.abs(cmfs_matrix(W)).sum(1) + xyz_sum_rgb(rgb) + 1e-12
    np.testing.assert_array_less(np.abs(xyz_sum_spectra(out) - xyz_sum_rgb(rgb)), 1e-9 * scale)


def test_zero_shape_guard_is_flat_and_no_nan():
    S = np.zeros((2, 2, 31), np.float32)
    S[0, 0] = np.nan
    S[1, 1] = -1.0
    rgb = np.full((2, 2, 3), 2.0, np.float32)
    out = restore_luminance(S, rgb, W)
    assert np.all(np.isfinite(out))
    # Every guarded pixel is a flat spectrum with the input's X+Y+Z.
    assert np.allclose(out, out[..., :1])
    np.testing.assert_allclose(xyz_sum_spectra(out), xyz_sum_rgb(rgb), rtol=1e-6)
    assert np.all(restore_luminance(S, np.zeros_like(rgb), W) == 0)


def test_restoring_the_truths_own_shape_gives_the_truth():
    rng = np.random.default_rng(3)
    gt = rng.uniform(0.1, 5, (6, 5, 31)) * rng.uniform(1, 1e3, (6, 5, 1))
    rgb = gt @ cmfs_matrix(W) @ XYZ_TO_SRGB.T      # unclipped, so XYZ round-trips exactly
    shape = gt / gt.max(-1, keepdims=True)          # any per-pixel scaling of the truth
    np.testing.assert_allclose(restore_luminance(shape, rgb, W), gt, rtol=1e-9)


def test_reinhard_and_inverse():
    x = np.array([0.0, 0.5, 1.0, 9.0, 1e6, -3.0], np.float32)
    y = reinhard(x)
    assert y.dtype == np.float32
    np.testing.assert_allclose(y, [0, 1 / 3, 0.5, 0.9, 1e6 / (1 + 1e6), 0], rtol=1e-6)
    np.testing.assert_allclose(inverse_reinhard(reinhard(x[:4].astype(np.float64))), x[:4],
                               rtol=1e-12)
    big = inverse_reinhard(np.array([1.0, 2.0, np.float64(-1)]))
    assert np.all(np.isfinite(big)) and big[2] == 0


# --- Known answer: pre-processing helps a model whose input range is bounded -------------------
def _bounded_world():
    """A 3-D spectral world where an exact RGB → spectrum inverse exists, and a model
    that is exact for inputs in [0, 1] but saturates above (like a network trained on LDR)."""
    wl = W
    B = np.stack([np.exp(-0.5 * ((wl - c) / 45.0) ** 2) for c in (450, 540, 620)])  # (3, 31)
    M = B @ cmfs_matrix(wl) @ XYZ_TO_SRGB.T                                        # c → rgb
    Minv = np.linalg.inv(M)

    def bounded(rgb):
        return (np.clip(rgb, 0, 1) @ Minv @ B).astype(np.float32)

    return B, M, FunctionModel(bounded, name="bounded", wavelengths=wl)


def test_reinhard_helps_a_luminance_sensitive_model_on_hdr_input():
    B, M, model = _bounded_world()
    rng = np.random.default_rng(11)
    coef = rng.uniform(0.2, 1.0, (32, 32, 3))
    coef /= (coef @ M).max() * 1.05
    rgb_ldr = coef @ M
    assert rgb_ldr.min() > 0 and rgb_ldr.max() < 1        # the set-up is in range
    gt_ldr = coef @ B
    # Known answer 1: in range, without pre-processing the model is exact.
    pred = predict(model, rgb_ldr.astype(np.float32), preprocess=False, restore=True)
    assert sam_deg(pred, gt_ldr) < 0.05
    # HDR: the same scene 2–20× brighter; clipping destroys the colour, Reinhard keeps the
    # channel order. (Measured: SAM 11.8° → 9.0°; the gain shrinks as k grows, since
    # x/(1+x) also flattens towards grey, and at k ≈ 1–2 Reinhard hurts: 1.4° → 4.7°.)
    k = np.exp(rng.uniform(np.log(2), np.log(20), (32, 32, 1)))
    rgb = (rgb_ldr * k).astype(np.float32)
    gt = gt_ldr * k
    off = predict(model, rgb, preprocess=False, restore=True)
    on = predict(model, rgb, preprocess=True, restore=True)
    # Known answer 2: without pre-processing the output is the restored spectrum of clip(rgb).
    expect = restore_luminance((np.clip(rgb, 0, 1) @ np.linalg.inv(M) @ B).astype(np.float32),
                               rgb, W)
    np.testing.assert_allclose(off, expect, rtol=1e-4, atol=1e-6)
    sam_off, sam_on = sam_deg(off, gt), sam_deg(on, gt)
    assert sam_on < 0.85 * sam_off, (sam_on, sam_off)
    # Restoration gives both the input's brightness, so the remaining error is shape only.
    np.testing.assert_allclose(xyz_sum_spectra(on), xyz_sum_rgb(rgb), rtol=1e-4)


def test_reinhard_does_not_help_exposure_equivariant_baselines():
    """Documented: Smits/Mallett/regression scale with the input, so x/(1+x) only distorts
    chromaticity; luminance restoration already handles brightness."""
    from mehs.ssr.baselines import Smits1999

    B, M, _ = _bounded_world()
    rng = np.random.default_rng(12)
    coef = rng.uniform(0.2, 1.0, (16, 16, 3)) * np.exp(rng.uniform(0, 5, (16, 16, 1)))
    rgb = (coef @ M).astype(np.float32)
    gt = coef @ B
    sm = Smits1999()
    off = sam_deg(predict(sm, rgb, preprocess=False), gt)
    on = sam_deg(predict(sm, rgb, preprocess=True), gt)
    assert on > off


def test_switch_restore_off_with_preprocess_inverts_reinhard():
    f = FunctionModel(lambda x: np.repeat(x[..., 1:2], 31, -1), name="g")
    rgb = np.full((2, 2, 3), 3.0, np.float32)
    out = predict(f, rgb, preprocess=True, restore=False)
    np.testing.assert_allclose(out, 3.0, rtol=1e-5)
    assert np.all(predict(f, rgb, preprocess=False, restore=False) == 3.0)


def test_overwrite_writes_into_the_spectra_and_gives_the_same_numbers():
    rng = np.random.default_rng(3)
    rgb = rng.random((6, 5, 3), dtype=np.float32) * 4
    for fallback in (False, True):
        S = rng.random((31, 6, 5), dtype=np.float32).transpose(1, 2, 0)   # band-major (torch)
        if fallback:
            S[0, 0] = 0.0                       # a flat-spectrum fallback pixel as well
        want = restore_luminance(S, rgb, WAVELENGTHS_31)
        got = restore_luminance(S, rgb, WAVELENGTHS_31, overwrite=True)
        np.testing.assert_array_equal(got, want)
        # (the fallback's pixels are filled in place too, session 29)
        assert np.shares_memory(got, S)
    ro = rng.random((6, 5, 31), dtype=np.float32)
    ro.flags.writeable = False
    np.testing.assert_array_equal(restore_luminance(ro, rgb, WAVELENGTHS_31, overwrite=True),
                                  restore_luminance(ro, rgb, WAVELENGTHS_31))
