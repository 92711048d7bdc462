"""Simulated scenes against outside truth: scene kinds at every entry point, the ramp's steps,
lights past colour-science's tables (CIE A formula, CIE D series to 830 nm, tungsten = Planck),
ColorChecker colours against colour-science's own integration."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from mehs.capture.scene import (SCENE_KINDS, SPECIM_IQ_WAVELENGTHS, colorchecker_reflectances,
                                illuminant_spectrum, make_scene)

colour = pytest.importorskip("colour")

WL = np.asarray(SPECIM_IQ_WAVELENGTHS)
VIS = (WL >= 400) & (WL <= 700)


def _rel(v, wl):
    v = np.asarray(v, np.float64)
    return v / v[(wl >= 400) & (wl <= 700)].mean()


def _ramp_step_medians(scene):
    """Median visible radiance of each of the ramp's 8 steps (its rows, as make_scene lays them)."""
    lines, samples = scene.radiance.shape[:2]
    y = scene.radiance[..., VIS].mean(axis=2)
    u = np.arange(samples) / (samples - 1)
    v = np.arange(lines) / (lines - 1)
    step = np.clip((u * 8).astype(int), 0, 7)
    rows = (v >= 0.06) & (v <= 0.94)
    return np.array([np.median(y[rows][:, step == k]) for k in range(8)])


def test_every_entry_point_builds_the_scene_kind_it_is_given():
    """make_scene, `mehs sim-device` and `mehs capture --simulate` (one argument parser) and
    the demo's response ladder: the kind reaches the radiance; no two kinds are alike."""
    from mehs.cli import capture as capture_cli
    from mehs.cli import sim_device

    cubes = {k: make_scene(k, 24, 24, seed=3) for k in SCENE_KINDS}
    for a in SCENE_KINDS:
        assert cubes[a].info["kind"] == a
        for b in SCENE_KINDS:
            if a < b:
                assert not np.allclose(cubes[a].radiance, cubes[b].radiance), (a, b)
    for configure in (sim_device.configure, capture_cli.configure):
        parser = argparse.ArgumentParser()
        configure(parser)
        for kind in SCENE_KINDS:
            args = parser.parse_args(["--scene", kind, "--size", "24", "--seed", "3"])
            dev = sim_device.build_devices(args)
            np.testing.assert_array_equal(dev.world.scene.radiance, cubes[kind].radiance)
            assert dev.world.scene.info["kind"] == kind
    # the demo's ladder asks for the ramp without a lamp: 4 decades of neutral steps
    med = _ramp_step_medians(make_scene("ramp", 64, 64, illuminant="D65", source_ratio=0.0))
    assert np.all(np.diff(med) < 0) and med[0] / med[-1] > 5e3


@pytest.mark.parametrize("size", [16, 48, 64])
def test_the_ramp_with_its_lamp_still_steps_down_monotonically(size):
    """Before: the lamp sat on the darkest steps and its glare (1/r³) turned the ramp round —
    step medians 0.89, 0.25, 0.080, 0.054, 0.087, 0.20, 0.38, 0.32 at 64², the far half as bright
    as the chart's patches. Now the lamp is on the brightest step."""
    s = make_scene("ramp", size, size)
    med = _ramp_step_medians(s)
    assert np.all(np.diff(med) < 0), med
    assert med[0] / med[-1] > 50, med
    # the lamp covers none of steps 2–8 (at 16², a 2-pixel step cannot hold its 3-pixel disc)
    lum = s.radiance[..., VIS].mean(axis=2)
    core = lum > 0.9 * s.info["source_ratio"]
    u = np.arange(size) / (size - 1)
    assert core.any() and (size < 32 or not core[:, u >= 1 / 8].any())


def test_illuminant_a_is_the_cie_formula():
    """CIE 015 defines A with c₂ = 1.435e-2 m·K at 2848 K; Planck at 2856 K with c₂ = 1.4388e-2
    was 0.09 % off colour-science's table (8.7e-4), the formula is within its rounding."""
    sd = colour.SDS_ILLUMINANTS["A"]
    x = np.asarray(sd.wavelengths, np.float64)
    x, v = x[x >= 380], np.asarray(sd.values, np.float64)[x >= 380]
    got = illuminant_spectrum("A", x)
    assert np.abs(got / _rel(v, x) - 1).max() < 2e-5


@pytest.mark.parametrize("name,cct", [("D65", 6500), ("D50", 5000), ("D75", 7500)])
def test_daylight_illuminants_follow_the_cie_d_series_to_830_nm(name, cct):
    """colour-science's D65 table stops at 780 nm, CIE's at 830 nm; holding the 760–780 mean
    was up to 14 % off the CIE values in 780–830 nm (the O₂ and H₂O dips of the D series)."""
    xy = colour.temperature.CCT_to_xy_CIE_D(cct * 1.4388 / 1.4380)
    d = colour.sd_CIE_illuminant_D_series(xy)
    ref = _rel(np.interp(WL, d.wavelengths, d.values), WL)
    got = illuminant_spectrum(name, WL)
    band = WL <= 830
    assert np.abs(got[band] / ref[band] - 1).max() < 1e-4
    # and the table's own values where it has them
    t = colour.SDS_ILLUMINANTS[name]
    inside = WL <= 780
    np.testing.assert_allclose(got[inside], _rel(np.interp(WL, t.wavelengths, t.values), WL)[inside],
                               rtol=1e-4)


def _fit_kelvin(w, v):
    """Brute-force Planck temperature of a table's shape from 500 nm (log least squares)."""
    k = w >= 500
    ts = np.arange(1500.0, 5000.0, 1.0)
    best = min(ts, key=lambda t: np.var(np.log(v[k]) - np.log(
        colour.sd_blackbody(t, colour.SpectralShape(w[k][0], w[k][-1], 1))[w[k]])))
    return float(best)


@pytest.mark.parametrize("name", ["ISO 7589 Studio Tungsten", "Incandescent"])
def test_tungsten_lamps_keep_rising_as_planck_past_their_table(name):
    """A filament is near a grey body: past its table (690 / 780 nm) the SPD follows Planck's
    law (colour.sd_blackbody at the table's fitted temperature), not the table's last value
    (18–21 % low at 1000 nm before)."""
    from mehs.scenes.library import Light, light_spectrum

    src = colour.SDS_ILLUMINANTS if name in colour.SDS_ILLUMINANTS else colour.SDS_LIGHT_SOURCES
    sd = src[name]
    w, v = np.asarray(sd.wavelengths, np.float64), np.asarray(sd.values, np.float64)
    t = _fit_kelvin(w, v)
    bb = colour.sd_blackbody(t, colour.SpectralShape(360, 1010, 1))
    got = light_spectrum(Light("tungsten", name), WL)
    beyond = WL > w[-1] + 5
    ratio = got[beyond] / np.interp(WL[beyond], bb.wavelengths, bb.values)
    assert np.ptp(ratio) / ratio.mean() < 0.01, (t, ratio.min(), ratio.max())
    assert got[-1] > 1.1 * got[np.searchsorted(WL, w[-1])]


def test_illuminant_a_is_one_light_in_the_chart_scenes_and_the_natural_scenes():
    """The natural scenes' named light "A" held its 780 nm value (18 % below CIE A at 1000 nm)
    while make_scene evaluated A everywhere: the same name, two spectra."""
    from mehs.scenes.library import Light, light_spectrum

    np.testing.assert_allclose(light_spectrum(Light("tungsten", "A"), WL, 7.0),
                               illuminant_spectrum("A", WL, 7.0), rtol=1e-9)


def test_colorchecker_colours_match_colour_science_under_d65():
    """The 24 patches sampled on the Specim grid with mehs's D65, integrated by hand, against
    colour.sd_to_XYZ of the same N. Ohta spectra: ΔE2000 ≤ 0.1 (measured 0.064)."""
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    c = np.stack([np.interp(WL, cmfs.wavelengths, cmfs.values[:, i], left=0, right=0)
                  for i in range(3)], 1)
    e = illuminant_spectrum("D65", WL)
    dw = np.gradient(WL)
    xyz = (colorchecker_reflectances(WL) * e * dw) @ c / np.sum(e * c[:, 1] * dw)
    ref = np.stack([colour.sd_to_XYZ(sd, cmfs, colour.SDS_ILLUMINANTS["D65"]) / 100
                    for sd in colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values()])
    wp = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    de = colour.delta_E(colour.XYZ_to_Lab(xyz, wp), colour.XYZ_to_Lab(ref, wp), method="CIE 2000")
    assert de.max() < 0.1, de.max()


def test_the_ramp_is_the_chart_white_stepping_over_4_decades_and_never_above_1():
    """L = ρ·E (relative radiance, π and the absolute scale left out): without lamp, shading and
    texture each step over the illuminant is the white patch × 10^(−4k/7), and the top step
    reflects at most all the light (it was the white patch / its mean: 1.022 in the red)."""
    s = make_scene("ramp", 64, 64, source_ratio=0.0, shading=0.0, texture=0.0)
    rho = s.radiance[32] / illuminant_spectrum("D65", WL, 7.0)
    white = colorchecker_reflectances(WL)[18]
    step = np.clip((np.arange(64) / 63 * 8).astype(int), 0, 7)
    for k in range(8):
        np.testing.assert_allclose(rho[step == k] / white, 10 ** (-4 * k / 7) / white.max(), rtol=1e-5)
    assert rho.max() <= 1.0 + 1e-6    # float32 radiance
