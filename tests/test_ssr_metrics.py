"""SSR metrics against hand-computed values and the NTIRE / MST++ reference formulas."""

import math

import numpy as np
import pytest

from mehs.errors import InputError
from mehs.ssr.evaluate import summarise
from mehs.ssr.metrics import image_metrics, mrae, psnr, rmse, sam_deg, sam_map


# --- reference formulas, transcribed from MST++ (utils.py: Loss_MRAE, Loss_RMSE, Loss_PSNR) in numpy
def ref_mrae(outputs, label):
    error = np.abs(outputs - label) / label
    return float(np.mean(error.reshape(-1)))


def ref_rmse(outputs, label):
    error = outputs - label
    return float(np.sqrt(np.mean((error ** 2).reshape(-1))))


def ref_psnr(im_true, im_fake, data_range=255):
    # MST++ clamps to [0, 1], scales by data_range and averages the MSE over C·H·W.
    t = np.clip(im_true, 0, 1) * data_range
    f = np.clip(im_fake, 0, 1) * data_range
    err = np.mean((t - f) ** 2)
    return float(10 * np.log10(data_range ** 2 / err))


def ref_sam_deg(x, y):
    # NTIRE-style SAM: mean over pixels of arccos of the normalised dot product, degrees.
    num = np.sum(x * y, -1)
    den = np.linalg.norm(x, axis=-1) * np.linalg.norm(y, axis=-1)
    return float(np.degrees(np.arccos(np.clip(num / den, -1, 1))).mean())


@pytest.fixture
def rand_pair():
    rng = np.random.default_rng(7)
    gt = rng.uniform(0.05, 1.0, (12, 9, 31))
    pred = np.clip(gt + rng.normal(0, 0.05, gt.shape), 0.001, 1)
    return pred, gt


def test_metrics_match_mstpp_formulas(rand_pair):
    pred, gt = rand_pair
    assert mrae(pred, gt) == pytest.approx(ref_mrae(pred, gt), rel=1e-12)
    assert rmse(pred, gt) == pytest.approx(ref_rmse(pred, gt), rel=1e-12)
    # psnr with peak=1 on [0, 1] data is MST++'s data_range-independent value.
    assert psnr(pred, gt, peak=1.0) == pytest.approx(ref_psnr(gt, pred), rel=1e-10)
    assert sam_deg(pred, gt) == pytest.approx(ref_sam_deg(pred, gt), rel=1e-10)
    m = image_metrics(pred, gt, peak=1.0)
    assert m["mrae"] == pytest.approx(ref_mrae(pred, gt), rel=1e-12)
    assert m["psnr"] == pytest.approx(ref_psnr(gt, pred), rel=1e-10)
    assert m["sam"] == pytest.approx(ref_sam_deg(pred, gt), rel=1e-10)


def test_hand_computed_values():
    gt = np.array([[[1.0, 0.0]], [[2.0, 2.0]]])        # (2, 1, 2)
    pred = np.array([[[0.0, 1.0]], [[1.0, 3.0]]])
    # SAM: 90° and angle between (1,3) and (2,2): cos = 8 / (√10 · √8)
    a2 = math.degrees(math.acos(8 / (math.sqrt(10) * math.sqrt(8))))
    assert sam_deg(pred, gt) == pytest.approx((90 + a2) / 2)
    # MRAE: the y = 0 element is excluded → (|0-1|/1 + 1/2 + 1/2) / 3
    val, n_excl = mrae(pred, gt, return_count=True)
    assert val == pytest.approx(2 / 3) and n_excl == 1
    # RMSE over all four elements: errors 1, 1, 1, 1
    assert rmse(pred, gt) == pytest.approx(1.0)
    # PSNR with the default peak = max(gt) = 2: 10·log10(4 / 1)
    assert psnr(pred, gt) == pytest.approx(10 * math.log10(4.0))


def test_sam_identical_and_scaled_is_zero(rand_pair):
    _, gt = rand_pair
    assert sam_deg(gt, gt) == pytest.approx(0, abs=1e-5)
    assert sam_deg(gt * 123.4, gt) == pytest.approx(0, abs=1e-5)
    assert sam_deg(gt * 1e-6, gt) == pytest.approx(0, abs=1e-5)


def test_sam_zero_norm_excluded_and_counted(rand_pair):
    pred, gt = rand_pair
    pred = pred.copy()
    pred[0, :3] = 0
    gt = gt.copy()
    gt[1, 0] = 0
    val, n = sam_deg(pred, gt, return_count=True)
    keep = np.ones(gt.shape[:2], bool)
    keep[0, :3] = keep[1, 0] = False
    assert n == 4
    assert val == pytest.approx(ref_sam_deg(pred[keep], gt[keep]))
    assert np.isnan(sam_map(pred, gt)[0, 0])
    m = image_metrics(pred, gt)
    assert m["sam_excluded"] == 4 and m["sam"] == pytest.approx(val)


def test_mrae_zeros_ignored_not_infinite(rand_pair):
    pred, gt = rand_pair
    gt = gt.copy()
    gt[2, 3, 5] = 0.0
    gt[4, 4, :] = 0.0
    val, n = mrae(pred, gt, return_count=True)
    ok = gt > 0
    assert n == 1 + 31
    assert val == pytest.approx(float(np.mean(np.abs(pred[ok] - gt[ok]) / gt[ok])))
    assert math.isfinite(val)
    assert image_metrics(pred, gt)["mrae_excluded"] == 32


def test_mask_and_crop_respected(rand_pair):
    pred, gt = rand_pair
    bad = pred.copy()
    bad[5, 5] = 50.0                       # a wildly wrong pixel …
    valid = np.ones(gt.shape[:2], bool)
    valid[5, 5] = False                    # … that the mask removes
    assert mrae(bad, gt, valid=valid) == pytest.approx(mrae(pred, gt, valid=valid))
    assert mrae(bad, gt) > mrae(pred, gt) * 2
    cropped = mrae(pred, gt, crop=2)
    assert cropped == pytest.approx(ref_mrae(pred[2:-2, 2:-2], gt[2:-2, 2:-2]))
    with pytest.raises(InputError):
        mrae(pred, gt, crop=6)
    with pytest.raises(InputError):
        mrae(pred, gt, valid=np.ones((3, 3), bool))


def test_nan_input_rejected_and_empty_gives_none(rand_pair):
    pred, gt = rand_pair
    p = pred.copy()
    p[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        image_metrics(p, gt)
    none = image_metrics(pred, gt, valid=np.zeros(gt.shape[:2], bool))
    assert none["sam"] is None and none["mrae"] is None and none["psnr"] is None
    assert none["n_pixels"] == 0


def test_psnr_identical_is_capped_not_inf(rand_pair):
    _, gt = rand_pair
    assert psnr(gt, gt) == pytest.approx(120.0)


def test_summary_never_nan():
    rows = [
        {"scene": "a", "input": "hdr", "preprocess": "off", "restore": True, "model": "m",
         "sam": 2.0, "mrae": None, "rmse": 1.0, "psnr": 30.0, "sam_excluded": 3,
         "mrae_excluded": 0, "seconds": 0.1},
        {"scene": "b", "input": "hdr", "preprocess": "off", "restore": True, "model": "m",
         "sam": None, "mrae": None, "rmse": 3.0, "psnr": float("nan"), "sam_excluded": 0,
         "mrae_excluded": 5, "seconds": 0.1},
    ]
    (s,) = summarise(rows, {"hdr-pp_off-lr_on-m": [[None, 0.5], [None, 0.7]]})
    assert s["sam"] == 2.0 and s["sam_undefined"] == 1
    assert s["mrae"] is None and s["mrae_undefined"] == 2
    assert s["psnr"] == 30.0 and s["rmse"] == 2.0
    assert s["band_mrae"] == [None, pytest.approx(0.6)]
    assert s["sam_excluded"] == 3 and s["mrae_excluded"] == 5
    for k, v in s.items():
        assert not (isinstance(v, float) and math.isnan(v)), k
