"""The simulated sensor against the EMVA 1288 linear camera model, with the full well
as a charge limit and read noise added at read-out.

EMVA 1288 (release 4.0): ``μ_y = μ_y.dark + K·μ_e``, ``σ_y² = K²·σ_d² + σ_q² + K·(μ_y − μ_y.dark)``
with ``σ_q² = 1/12 DN²``; dark current adds ``μ_I·t`` electrons and their shot noise.
A pixel's well holds at most ``full_well_e`` electrons; the read noise ``σ_d`` joins
afterwards, so a well-clipped pixel reads ``K·FW + black`` DN with variance
``K²σ_d² + 1/12``, unless the ADC's largest code comes first. The expected numbers are
the configured parameters', never the simulator's own output.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from mehs.capture.sensor import SensorModel

K, READ, BLACK = 0.25, 8.0, 32.0


def _sensor(**kw):
    base = dict(qe=np.ones(2), gain_dn_per_e=K, read_noise_e=READ, dark_current_e_per_ms=0.0,
                column_fpn_sigma=0.0, black_level_dn=BLACK, radiance_to_e_per_ms=1.0, seed=5)
    base.update(kw)
    return SensorModel(**base)


def _frames(s, electrons, t=1.0, lines=3, samples=20000, shutter_open=True):
    """float64 DN of ``lines`` lines of ``samples × 2`` pixels at mean ``electrons`` e⁻/ms."""
    rad = np.full((samples, 2), electrons, np.float32)
    return np.stack([s.expose_line(rad, t, line_index=i, shutter_open=shutter_open)
                     for i in range(lines)]).astype(np.float64)


def test_well_clipped_pixel_reads_the_saturation_capacity_plus_read_noise():
    # 14 000 e⁻ × 0.25 + 32 = 3532 DN < 4095: the well clips first, the read noise
    # (8 e⁻ = 2 DN) still spreads the plateau. Before: every pixel exactly 3532 (σ 0).
    fw = 14000.0
    z = _frames(_sensor(full_well_e=fw), 10 * fw)
    assert z.mean() == pytest.approx(K * fw + BLACK, abs=0.05)
    assert z.var() == pytest.approx(K * K * READ ** 2 + 1 / 12, rel=0.03)
    # EMVA saturation capacity μ_e.sat = (μ_y.sat − μ_y.dark) / K
    dark = _frames(_sensor(full_well_e=fw), 0.0, shutter_open=False)
    assert (z.mean() - dark.mean()) / K == pytest.approx(fw, abs=0.5)
    # the plateau is Gaussian read noise: ~68 % of the pixels within ±1 σ
    assert np.mean(np.abs(z - (K * fw + BLACK)) <= 2.0) == pytest.approx(
        stats.norm.cdf(2.5 / 2.0207) - stats.norm.cdf(-2.5 / 2.0207), abs=0.01)


def test_whichever_clip_comes_first_adc_or_well():
    # the well at 4093 DN, 2 DN of read noise after it: the ADC (4095) clips the
    # upper tail, P(x ≥ 4094.5) = P(N > 0.75); before, no pixel left 4093
    fw = (4093.0 - BLACK) / K
    z = _frames(_sensor(full_well_e=fw), 10 * fw)
    sigma = np.sqrt((K * READ) ** 2)
    assert np.mean(z == 4095) == pytest.approx(stats.norm.sf(1.5 / sigma), abs=0.01)
    assert z.min() < 4093 - 3 * sigma
    # the default well (20 000 e⁻ → 5032 DN) lies far above the ADC range: all 4095
    z = _frames(_sensor(full_well_e=20000.0), 200000.0, lines=1, samples=2000)
    assert np.all(z == 4095)


def test_shot_noise_is_clipped_at_the_well_then_read_noise_added():
    # λ = FW: the shot noise (σ = √FW) half clipped. E[min(X, FW)] = FW − σ·φ(0),
    # Var = σ²·(1/2 − 1/(2π)); read noise (independent, after the clip) adds σ_read².
    fw = 10000.0
    z = _frames(_sensor(full_well_e=fw, read_noise_e=30.0), fw, lines=4)
    sd = np.sqrt(fw)
    mean_e = fw - sd * stats.norm.pdf(0)
    var_e = sd ** 2 * (0.5 - 1 / (2 * np.pi)) + 30.0 ** 2
    assert z.mean() == pytest.approx(K * mean_e + BLACK, abs=0.1)
    assert z.var() == pytest.approx(K * K * var_e + 1 / 12, rel=0.03)


@pytest.mark.parametrize("read", [8.0, 4.0, 2.0])
def test_photon_transfer_mean_and_variance_follow_emva1288(read):
    # μ_y = K(μ_e + μ_I t) + black;  σ_y² = K²(σ_read² + μ_I t + μ_e) + 1/12, at every t
    s = _sensor(read_noise_e=read, dark_current_e_per_ms=3.0)
    for rate, t in [(0.0, 1.0), (5.0, 4.0), (40.0, 10.0), (300.0, 20.0)]:
        z = _frames(s, rate, t=t)
        mu_e, dark_e = rate * t, 3.0 * t
        assert z.mean() == pytest.approx(K * (mu_e + dark_e) + BLACK, abs=0.05)
        assert z.var() == pytest.approx(K * K * (read ** 2 + dark_e + mu_e) + 1 / 12, rel=0.03)


def test_read_noise_floor_of_dark_frames():
    # shutter closed: μ = black + K·μ_I·t, σ² = K²(σ_read² + μ_I·t) + 1/12 (EMVA σ_y.dark²)
    s = _sensor(dark_current_e_per_ms=2.0)
    for t in (1.0, 50.0):
        z = _frames(s, 0.0, t=t, shutter_open=False)
        assert z.mean() == pytest.approx(BLACK + K * 2.0 * t, abs=0.05)
        assert z.var() == pytest.approx(K * K * (READ ** 2 + 2.0 * t) + 1 / 12, rel=0.03)


@pytest.mark.parametrize("read, lam", [(0.0, 50.0), (2.0, 100.0)])
def test_shot_noise_is_poisson_where_its_skew_shows(read, lam):
    # Poisson + Gaussian: third cumulant λ, skewness λ/(λ + σ² + 1/12)^1.5 at K = 1
    # (0.141 and 0.094 here). The normal stand-in (skew 0) was used for every λ ≥ 16 e⁻.
    s = _sensor(gain_dn_per_e=1.0, read_noise_e=read, black_level_dn=10.0)
    z = _frames(s, lam, lines=5)
    want = lam / (lam + read ** 2 + 1 / 12) ** 1.5
    assert stats.skew(z.ravel()) == pytest.approx(want, abs=0.02)
    assert z.var() == pytest.approx(lam + read ** 2 + 1 / 12, rel=0.03)
