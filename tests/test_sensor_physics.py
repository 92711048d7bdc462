"""Audit of the simulated sensor and scenes against independent references.

References: the EMVA 1288 linear camera model (mean and variance of a pixel),
colour-science's tabulated SPDs integrated over a Gaussian band response by
plain quadrature (not mehs code), and mehs' own calibration for the
simulator-truth consistency.
"""

from __future__ import annotations

import numpy as np
import pytest

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
from mehs.capture.sensor import SensorModel
from mehs.errors import InputError

WL = SPECIM_IQ_WAVELENGTHS[(SPECIM_IQ_WAVELENGTHS >= 400) & (SPECIM_IQ_WAVELENGTHS <= 760)]
VIS = (WL >= 400) & (WL <= 700)


def _sd(name):
    import colour

    src = colour.SDS_ILLUMINANTS if name in colour.SDS_ILLUMINANTS else colour.SDS_LIGHT_SOURCES
    sd = src[name]
    return np.asarray(sd.wavelengths, float), np.asarray(sd.values, float)


def _band_reference(name, wl, fwhm=7.0):
    """The SPD seen through untruncated Gaussian bands (±6σ quadrature), mean 1 over 400–700 nm."""
    w, v = _sd(name)
    sig = fwhm / (2 * np.sqrt(2 * np.log(2)))
    out = np.empty(wl.size)
    for i, c in enumerate(wl):
        x = np.linspace(c - 6 * sig, c + 6 * sig, 4001)
        g = np.exp(-0.5 * ((x - c) / sig) ** 2)
        out[i] = np.trapezoid(g * np.interp(x, w, v), x) / np.trapezoid(g, x)
    return out / out[(wl >= 400) & (wl <= 700)].mean()


def test_pixel_mean_and_variance_follow_emva1288():
    # μ = K(η·L·s·t + d·t) + offset;  σ² = K²(μ_e + σ_read²) + 1/12 (quantisation)
    k, rn, dark, scale = 0.25, 8.0, 2.0, 400.0
    s = SensorModel(qe=np.ones(2), gain_dn_per_e=k, read_noise_e=rn, dark_current_e_per_ms=dark,
                    column_fpn_sigma=0.0, black_level_dn=32.0, radiance_to_e_per_ms=scale)
    for L, t in [(0.0, 1.0), (0.1, 2.0), (1.0, 5.0), (2.0, 9.0)]:
        z = np.stack([s.expose_line(np.full((20000, 2), L, np.float32), t, line_index=i)
                      for i in range(3)]).astype(np.float64)
        mu_e = L * scale * t + dark * t
        assert z.mean() == pytest.approx(k * mu_e + 32.0, abs=0.05)
        assert z.var() == pytest.approx(k * k * (mu_e + rn ** 2) + 1 / 12, rel=0.03)


@pytest.mark.parametrize("name", ["HP1", "FL11"])
def test_line_spectrum_light_is_seen_through_the_band_response(name):
    # A 7 nm band collects the lamp's lines around it; sampling the SPD at the band
    # centre put the simulated white 40-60 % off what the same SPD calibrates to.
    s = make_scene(lines=8, samples=8, wavelengths=WL, illuminant=name, source_ratio=0)
    ref = _band_reference(name, WL, 7.0)
    err = np.abs(s.white_radiance / 0.99 / ref - 1)
    assert err.max() < 0.03, f"{name}: white tile vs band-averaged SPD off by {err.max():.3f}"


def test_natural_scene_lights_are_band_averaged():
    from mehs.scenes.natural import make_natural_scene

    s = make_natural_scene(16, wavelengths=WL, lighting="fluorescent", seed=3, source_ratio=0)
    direct, fill = s.info["lights"][:2]
    assert direct["name"] == fill["name"] and direct["kelvin"] is None
    # indoors the fill is the direct light, indirect: white = 0.99·(1 + level)·E
    e = s.white_radiance / 0.99 / (1 + fill["level"])
    err = np.abs(e / _band_reference(direct["name"], WL, 7.0) - 1)
    assert err.max() < 0.03, f"{direct['name']}: off by {err.max():.3f}"


def test_panel_calibration_under_a_line_lamp_recovers_the_simulated_responsivity(tmp_path):
    from mehs.calibration import calibrate_panel_relative
    from mehs.calibration.spectra import Spectrum
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene
    from mehs.synthesis.bracket import load_bracket

    wl = WL[WL <= 705]
    scene = make_scene(lines=8, samples=8, wavelengths=wl, illuminant="FL11", source_ratio=0)
    sim = simulate_bracket(scene, SensorModel(wavelengths=wl), [0.5, 2.0, 8.0, 32.0, 128.0])
    br = load_bracket(write_simulated_scene(sim, tmp_path / "fl11"))
    w, v = _sd("FL11")
    cal = calibrate_panel_relative(br, Spectrum(np.array([300.0, 1100.0]), np.array([0.99, 0.99]), "flat"),
                                   Spectrum(w, v, "FL11"), region="white")
    q = cal.responsivity.mean(axis=0) / sim.truth_dn_per_ms
    q = q[wl >= 420] / np.median(q[wl >= 420])
    # was 0.49..1.53 with point-sampled lights
    assert np.abs(q - 1).max() < 0.02


@pytest.mark.parametrize("kw", [dict(response="gamma", gamma=0.0), dict(response="gamma", gamma=-0.5),
                                dict(response="gamma", gamma=float("nan")),
                                dict(response="s-curve", s_amplitude=1.5), dict(bit_depth=12.5)])
def test_bad_sensor_response_parameters_are_refused(kw):
    with pytest.raises(InputError, match="gamma|s_amplitude|bit_depth"):
        SensorModel(**kw)


def test_wavelengths_not_in_nm_are_refused():
    from mehs.scenes.natural import make_natural_scene

    um = SPECIM_IQ_WAVELENGTHS / 1000.0
    with pytest.raises(InputError, match="nm"):
        make_scene(lines=8, samples=8, wavelengths=um)
    with pytest.raises(InputError, match="nm"):
        make_natural_scene(8, wavelengths=um)
    with pytest.raises(InputError, match="nm"):
        SensorModel(wavelengths=um).expose_line(np.ones((4, 204), np.float32), 1.0)
    with pytest.raises(InputError, match="fwhm"):
        make_scene(lines=8, samples=8, fwhm=np.full(10, 7.0))
