"""Parts of the noise-floor exclusion: the band noise model, the MRAE floor, the rule, the report."""

import numpy as np
import pytest

from mehs.dataset import noisefloor as nf
from mehs.errors import InputError

NOISE = {"gain_dn_per_e": 0.25, "read_noise_dn": 2.0, "dark_current_dn_per_ms": 0.5,
         "relative": 0.0, "source": "test"}


def test_band_model_is_the_poisson_pool_through_the_matrix():
    """One native band, identity matrix: σ² = (gain·X·T + Σ(read² + gain·D·t)) / T²."""
    t = np.array([1.0, 4.0, 16.0])
    m = nf.band_noise_model(NOISE, t, np.eye(31))
    T = t.sum()
    A = np.sum(4.0 + 0.25 * 0.5 * t)
    x = np.float32(3.0)
    s = nf.sigma(np.full(31, x), m)
    np.testing.assert_allclose(s ** 2, (0.25 * 3.0 * T + A) / T ** 2, rtol=1e-5)
    # averaging n independent bands divides the variance by n; a radiance scale s² / s
    m4 = nf.band_noise_model(NOISE, t, np.kron(np.eye(31), np.full((1, 4), 0.25)))
    np.testing.assert_allclose(nf.sigma(np.full(31, x), m4) ** 2, s ** 2 / 4, rtol=1e-5)
    ms = nf.scaled(m, 0.5)
    np.testing.assert_allclose(nf.sigma(np.full(31, x * 0.5), ms), s * 0.5, rtol=1e-5)


def test_unresolved_is_the_spectrum_snr_against_ten():
    m = nf.band_noise_model(NOISE, [1.0, 4.0], np.eye(31))
    s0 = float(nf.sigma(np.zeros(31), m)[0])
    # a flat spectrum at 9·σ and at 11·σ (σ taken at that level)
    y = np.zeros((1, 2, 31), np.float32)
    for i, k in enumerate((9.0, 11.0)):
        lv = k * s0
        for _ in range(20):                       # σ grows with the level (shot noise)
            lv = k * float(nf.sigma(np.full(31, lv), m)[0])
        y[0, i] = lv
    assert nf.unresolved(y, m).tolist() == [[True, False]]
    with pytest.raises(InputError):
        nf.unresolved(y, m, snr=0)


def test_model_refuses_bad_inputs():
    with pytest.raises(InputError, match="noise model"):
        nf.band_noise_model({"read_noise_dn": 2.0}, [1.0], np.eye(31))
    with pytest.raises(InputError):
        nf.band_noise_model(NOISE, [0.0, 1.0], np.eye(31))
    with pytest.raises(InputError, match="band noise model"):
        nf.sigma(np.zeros(31), {"format": "other"})


def test_image_metrics_mrae_floor_excludes_and_counts():
    from mehs.ssr.metrics import image_metrics

    gt = np.array([[[1.0, 0.01]], [[2.0, 4.0]]])            # (2, 1, 2)
    pred = gt * 1.1
    pred[0, 0, 1] = 0.5                                      # |0.5 − 0.01|/0.01 = 49
    base = image_metrics(pred, gt)
    assert base["mrae"] == pytest.approx((0.1 * 3 + 49) / 4)
    m = image_metrics(pred, gt, mrae_floor=np.array([0.1, 0.1]))
    assert m["mrae"] == pytest.approx(0.1)
    assert m["mrae_excluded"] == 1 and m["mrae_floor_excluded"] == 1
    # per element, with a valid mask and a crop-free image: same rows as the metric
    fl = np.zeros_like(gt)
    fl[1, 0, 1] = 5.0
    v = np.array([[True], [True]])
    m2 = image_metrics(pred, gt, valid=v, mrae_floor=fl)
    assert m2["mrae"] == pytest.approx((0.1 * 2 + 49) / 3)
    assert m2["band_mrae"][1] == pytest.approx(49.0)
    with pytest.raises(InputError, match="MRAE floor has shape"):
        image_metrics(pred, gt, mrae_floor=np.zeros(3))
    with pytest.raises(InputError, match="NaN"):
        image_metrics(pred, gt, mrae_floor=np.array([np.nan, 0.0]))


def test_rule_is_off_by_default_and_fires_when_set():
    from mehs.dataset.quality import QualityRules, judge

    q = {"noise_floor_fraction": 0.9}
    assert judge(q)[0] == "pass"
    st, why = judge(q, QualityRules(max_noise_floor_fraction=0.5))
    assert st == "fail" and "not resolved above the noise" in why[0]
    assert judge({"noise_floor_fraction": None}, QualityRules(max_noise_floor_fraction=0.5))[0] == "pass"
    with pytest.raises(InputError):
        QualityRules(max_noise_floor_fraction=1.5)


def test_report_row_shows_the_fraction():
    from mehs.dataset.report import _row

    row = _row({"id": "a", "status": "pass", "quality": {"noise_floor_fraction": 0.25}}, "test")
    assert "25" in row and row.count("<td>") == 10
