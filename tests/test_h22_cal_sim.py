"""Radiometric calibration held against the simulator's true radiance (audit h22).

Independent truth: the radiance handed to the simulated sensor (``Scene.radiance``
before any optics fall-off is applied), and the sensor's own DN/ms per unit radiance.
The simulator has no per-column responsivity of its own (its column pattern is an
offset, removed by the dark), so vignetting / PRNU is applied here as the optics
do: as a per-column factor on the radiance reaching the sensor, in the reference and
in the scene alike, while the truth stays the radiance in front of the lens.
"""

from __future__ import annotations

import numpy as np
import pytest

from mehs.calibration import (UNIT_RELATIVE, calibrate_panel_relative,
                              calibrate_source_absolute)
from mehs.calibration.spectra import Spectrum
from mehs.calibration.targets import make_target_scene, sphere_radiance
from mehs.errors import InputError

N = 24
SPHERE_TIMES = (40.8, 81.5, 163.0)
WINDOW_TIMES = (0.05, 2.31, 106.0)


def _sensor():
    from mehs.capture.sensor import SensorModel

    return SensorModel(seed=3)


def _bracket(tmp_path, name, scene, times, seed=1):
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene
    from mehs.synthesis.bracket import load_bracket

    sim = simulate_bracket(scene, _sensor(), times, seed=seed)
    write_simulated_scene(sim, tmp_path / name)
    return load_bracket(tmp_path / name), sim


def _certificate() -> Spectrum:
    g = np.arange(350.0, 1100.0 + 1e-9, 5.0)
    return Spectrum(g, sphere_radiance(g), "sphere certificate")


def _vignetting(n: int) -> np.ndarray:
    """Optics fall-off (≈ cos⁴, 25 % at the slit ends) times a 3 % pixel ripple (PRNU)."""
    s = np.arange(n, dtype=np.float64)
    return (1 - 0.25 * ((s - (n - 1) / 2) / (n / 2)) ** 2) * (1 + 0.03 * np.sin(1.7 * s))


def _sphere(profile_cols=None, profile_lines=None):
    sc = make_target_scene("sphere", N, N)
    if profile_cols is not None:
        sc.radiance = sc.radiance * np.asarray(profile_cols, dtype=np.float32)[None, :, None]
    if profile_lines is not None:
        sc.radiance = sc.radiance * np.asarray(profile_lines, dtype=np.float32)[:, None, None]
    return sc


def test_per_column_calibration_removes_vignetting_and_prnu(tmp_path):
    """Guard: absolute radiance per band and per column within 0.5 % of the truth."""
    from mehs.capture.scene import make_scene
    from mehs.synthesis.fuse import fuse_bracket

    vig = _vignetting(N)
    br, sim = _bracket(tmp_path, "sphere", _sphere(vig), SPHERE_TIMES)
    cal = calibrate_source_absolute(br, _certificate())
    win = make_scene("window", N, N, seed=0)
    truth = win.radiance.astype(np.float64)
    win.radiance = (win.radiance * vig[None, :, None]).astype(np.float32)
    wbr, _ = _bracket(tmp_path, "window", win, WINDOW_TIMES, seed=2)
    res = fuse_bracket(wbr, calibration=cal, response="linear")
    a = np.asarray(res.radiance.data, dtype=np.float64)
    rel = a / truth - 1
    # pixels with a good signal in the longest unsaturated exposure (≥ 300 DN)
    good = (res.mask == 0)[..., None] & (truth * sim.truth_dn_per_ms * WINDOW_TIMES[-1] > 300)
    per_col = np.array([np.median(rel[:, c][good[:, c]]) for c in range(N)])
    print(f"per-column median error: max |.| {np.abs(per_col).max():.4f}; median |err| "
          f"{np.median(np.abs(rel[good])):.4f}, p95 {np.percentile(np.abs(rel[good]), 95):.4f}")
    assert np.abs(per_col).max() < 0.005
    wl = wbr.wavelengths
    for lo, hi in ((420, 700), (700, 1000)):
        sel = good & ((wl >= lo) & (wl < hi))[None, None, :]
        assert abs(np.median(rel[sel])) < 0.005, (lo, hi)


@pytest.mark.parametrize("a,b", [(6, 17), (3, 9)])   # half the slit; under half (median unlit)
def test_reference_filling_part_of_the_slit_is_refused_by_name(tmp_path, a, b):
    s = np.arange(N)
    lit = np.where((s >= a) & (s <= b), 1.0, 0.02)   # the port covers columns a-b, stray light beside
    br, sim = _bracket(tmp_path, "sphere", _sphere(lit), SPHERE_TIMES)
    with pytest.raises(InputError, match=rf"fills columns {a}-{b} only") as ei:
        calibrate_source_absolute(br, _certificate())
    assert f"--no-flat-field --columns {a}-{b}" in str(ei.value)
    # the stated way out: one responsivity per band from the lit columns
    cal = calibrate_source_absolute(br, _certificate(), per_column=False, columns=f"{a}-{b}")
    ratio = cal.responsivity[0] / sim.truth_dn_per_ms
    assert abs(np.median(ratio) - 1) < 0.005 and np.percentile(np.abs(ratio - 1), 95) < 0.02
    assert cal.parameters["columns"] == [a, b]
    with pytest.raises(InputError, match="--no-flat-field"):
        calibrate_source_absolute(br, _certificate(), columns=f"{a}-{b}")


def test_reference_filling_part_of_the_lines_is_refused_by_name(tmp_path):
    rows = np.where(np.arange(N) < 16, 1.0, 0.0)    # the sphere leaves the view at line 16
    br, sim = _bracket(tmp_path, "sphere", _sphere(profile_lines=rows), SPHERE_TIMES)
    with pytest.raises(InputError, match=r"lines 16-23.*lines:0-15"):
        calibrate_source_absolute(br, _certificate())
    cal = calibrate_source_absolute(br, _certificate(), region="lines:0-15")
    ratio = cal.responsivity / sim.truth_dn_per_ms[None, :]
    assert abs(np.median(ratio) - 1) < 0.005


def test_one_responsivity_per_band_states_the_flat_field_it_leaves_out(tmp_path):
    """--no-flat-field on a vignetted camera: the stated uncertainty covers the columns' spread."""
    vig = _vignetting(N)
    br, sim = _bracket(tmp_path, "sphere", _sphere(vig), SPHERE_TIMES)
    cal = calibrate_source_absolute(br, _certificate(), per_column=False)
    # the error of applying one R to column s: R_true[s] / R
    true_r = sim.truth_dn_per_ms[None, :] * vig[:, None]
    err = true_r / cal.responsivity - 1
    rms = np.sqrt(np.mean(err ** 2, axis=0))
    stated = cal.uncertainty[0]
    print(f"per-column error RMS (median over bands) {np.median(rms):.4f}, stated "
          f"{np.median(stated):.4f}")
    assert np.median(stated / rms) > 0.9
    assert np.median(stated / rms) < 1.5     # and not wildly more
    assert 0.06 < cal.parameters["column_spread_median"] < 0.12


def _scatter_over_seeds(tmp_path, make, seeds):
    rs, us = [], []
    for k in seeds:
        cal = make(tmp_path, k)
        rs.append(cal.responsivity)
        us.append(cal.uncertainty)
    r, u = np.stack(rs), np.stack(us)
    return r.std(axis=0, ddof=1) / r.mean(axis=0), np.sqrt(np.mean(u ** 2, axis=0))


def test_white_line_uncertainty_matches_the_scatter_over_seeds(tmp_path):
    """The stated relative uncertainty of R from the white-reference line, per band range,
    against the scatter of R over captures with other noise seeds."""
    from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, illuminant_spectrum, make_scene

    wl = np.arange(300.0, 1101.0, 1.0)
    panel = Spectrum(np.array([300.0, 1100.0]), np.array([0.99, 0.99]), "flat 0.99")
    ill = Spectrum(wl, illuminant_spectrum("A", wl), "A")

    def make(tmp, k):
        br, _ = _bracket(tmp, f"w{k}", make_scene("window", 32, 32, seed=0), WINDOW_TIMES, seed=k)
        return calibrate_panel_relative(br, panel, ill, region="white")

    observed, stated = _scatter_over_seeds(tmp_path, make, range(1, 7))
    cw = SPECIM_IQ_WAVELENGTHS
    for lo, hi in ((397, 450), (450, 700), (700, 900), (900, 1010)):
        b = (cw >= lo) & (cw < hi)
        q = np.median(stated[:, b]) / np.median(observed[:, b])
        print(f"{lo}-{hi} nm: stated {np.median(stated[:, b]):.5f} observed "
              f"{np.median(observed[:, b]):.5f} ratio {q:.2f}")
        assert 0.67 < q < 1.5, (lo, hi, q)


def test_panel_relative_is_rho_s_over_pi_up_to_one_scale_against_colour_science(tmp_path):
    """Guard: a ColorChecker white under D65 (colour-science spectra) as the panel; a grey at
    another level under D65 calibrated with it is the truth times one scale, 1/mean(S)."""
    import colour

    from mehs.capture.scene import SPECIM_IQ_FWHM, SPECIM_IQ_WAVELENGTHS, Scene

    wl, fw = SPECIM_IQ_WAVELENGTHS, SPECIM_IQ_FWHM
    white = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]["white 9.5 (.05 D)"]
    d65 = colour.SDS_ILLUMINANTS["D65"]
    # truth: colour-science's own interpolation onto 0.1 nm, Gaussian bands, ρ·S/π
    x = np.arange(380.0, 780.0 + 1e-9, 0.1)
    rho_x = white.copy().interpolate(colour.SpectralShape(380, 780, 0.1)).values
    # D65 is tabulated about 100: /100 keeps the simulated panel below saturation
    s_x = d65.copy().interpolate(colour.SpectralShape(300, 780, 0.1)).values[800:] / 100
    assert s_x.size == x.size
    sig = fw / (2 * np.sqrt(2 * np.log(2)))
    w = np.exp(-0.5 * ((x[None, :] - wl[:, None]) / sig[:, None]) ** 2)
    inside = (wl - fw >= 380) & (wl + fw <= 780)
    with np.errstate(invalid="ignore", divide="ignore"):     # bands beyond 780 nm: 0/0
        # no light outside 380-780 nm (an LED-lit panel): bands --partial leaves out are dark
        L = np.where(inside, (w * (rho_x * s_x / np.pi)).sum(1) / w.sum(1), 0.0)
        s_band = (w * s_x).sum(1) / w.sum(1)

    def scene(level):
        cube = np.broadcast_to((level * L).astype(np.float32), (N, N, wl.size)).copy()
        return Scene("panel", cube, wl, fw, white_radiance=None, info={"kind": "panel"})

    rho = Spectrum(white.wavelengths, white.values, "ColorChecker white 9.5")
    ill = Spectrum(d65.wavelengths, d65.values, "D65")
    br, _ = _bracket(tmp_path, "panel", scene(1.0), (40.0, 80.0, 160.0))
    with pytest.raises(InputError, match="covers 380..780 nm"):
        calibrate_panel_relative(br, rho, ill, region="frame")
    cal = calibrate_panel_relative(br, rho, ill, region="frame", partial=True)
    assert cal.unit == UNIT_RELATIVE
    k = cal.bands
    assert np.all(inside[k])
    grey, _ = _bracket(tmp_path, "grey", scene(0.4), (80.0, 160.0, 320.0), seed=5)
    from mehs.synthesis.fuse import fuse_bracket

    res = fuse_bracket(grey, calibration=cal, response="linear")
    got = np.median(np.asarray(res.radiance.data, dtype=np.float64).reshape(-1, k.size), axis=0)
    ratio = got / (0.4 * L[k])
    vis = (wl[k] >= 400) & (wl[k] <= 700)
    # the one scale: S is normalised to a mean of 1 over the 400-700 nm bands
    vis_all = (wl >= 400) & (wl <= 700)
    expected = 1 / s_band[vis_all].mean()
    print(f"relative/true: median {np.median(ratio):.6f} expected {expected:.6f}, spread "
          f"p1-p99 {np.percentile(ratio / expected, 1):.4f}-{np.percentile(ratio / expected, 99):.4f}")
    assert np.all(np.abs(ratio[vis] / expected - 1) < 0.01)
    assert np.percentile(np.abs(ratio / expected - 1), 95) < 0.01


def test_partial_white_line_needs_no_light_in_the_bands_it_leaves_out(tmp_path):
    """An LED-lit white tile is dark in the NIR; --partial calibrates 397-774 nm from it
    (the illuminant table ends at 780 nm) instead of refusing the dark NIR bands."""
    from mehs.capture.scene import make_scene

    sc = make_scene("window", N, N, seed=0)
    wl = sc.wavelengths
    led = np.where(wl < 790, sc.white_radiance, 0.0).astype(np.float32)
    sc.white_radiance = led
    br, sim = _bracket(tmp_path, "led", sc, WINDOW_TIMES)
    ill = Spectrum(wl[wl < 785], led[wl < 785] / 0.99, "LED white tile SPD")
    panel = Spectrum(np.array([300.0, 1100.0]), np.array([0.99, 0.99]), "flat 0.99")
    cal = calibrate_panel_relative(br, panel, ill, region="white", partial=True)
    assert cal.calibrated_wavelengths[-1] < 785
    q = cal.responsivity.mean(axis=0) / sim.truth_dn_per_ms[cal.bands]
    assert np.percentile(np.abs(q / np.median(q) - 1), 95) < 0.03
