"""Pseudo-HDR-RGB and LDR-RGB (paper §3.1) against colour-science."""

import colour
import numpy as np
import OpenEXR
import pytest

from mehs.cube import SpectralCube
from mehs.errors import InputError
from mehs.io.exr import read_exr, write_exr_rgb
from mehs.rgb import (CMFS_NAME, WAVELENGTHS_31, XYZ_TO_SRGB, hdr_rgb, ldr_exposure, ldr_rgb,
                      luminance, spectra_to_XYZ)

SHAPE_31 = colour.SpectralShape(400, 700, 10)


def _d65():
    return colour.SDS_ILLUMINANTS["D65"].copy().align(SHAPE_31).values


def _colorchecker_under_d65():
    """(24, 31) radiance spectra of the ColorChecker (N Ohta) lit by D65."""
    cc = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    return np.stack([sd.copy().align(SHAPE_31).values for sd in cc.values()]) * _d65()


def test_matrix_is_the_iec_srgb_matrix_colour_uses():
    np.testing.assert_array_equal(XYZ_TO_SRGB,
                                  colour.models.RGB_COLOURSPACE_sRGB.matrix_XYZ_to_RGB)


def test_d65_maps_to_equal_rgb_times_Y():
    d65 = _d65() / _d65().max()  # normalised
    img = np.broadcast_to(d65, (2, 3, 31)).astype(np.float32)
    rgb = hdr_rgb(img, WAVELENGTHS_31)
    y = spectra_to_XYZ(d65, WAVELENGTHS_31)[1]
    # Sampling at 400..700/10 moves the white point by < 0.3 %.
    np.testing.assert_allclose(rgb / y, 1.0, atol=3e-3)
    # On the full 1 nm table (360..830) white is exact to the matrix's 4 digits.
    full = colour.SDS_ILLUMINANTS["D65"].copy().align(colour.SpectralShape(360, 830, 1))
    spec = full.values / 100.0
    rgb = hdr_rgb(spec[None, None, :], full.wavelengths)[0, 0]
    np.testing.assert_allclose(rgb / spectra_to_XYZ(spec, full.wavelengths)[1], 1.0, atol=3e-4)


def test_colorchecker_agrees_with_colour_science():
    radiance = _colorchecker_under_d65()
    mine = hdr_rgb(radiance.reshape(4, 6, 31).astype(np.float64), WAVELENGTHS_31).reshape(24, 3)

    cmfs = colour.MSDS_CMFS[CMFS_NAME].copy().align(SHAPE_31)
    ref = []
    for spd in radiance:
        sd = colour.SpectralDistribution(spd, SHAPE_31.wavelengths)
        # Emissive: no illuminant, k = 100/Σȳ (0..100 scale) → divide by 100 for k = 1/Σȳ.
        xyz = colour.sd_to_XYZ(sd, cmfs, method="Integration") / 100.0
        # sRGB's own white (D65): no chromatic adaptation; linear (no CCTF).
        ref.append(colour.XYZ_to_sRGB(xyz, chromatic_adaptation_transform=None,
                                      apply_cctf_encoding=False))
    ref = np.maximum(np.array(ref), 0)
    assert ref.max() > 1  # unnormalised scale
    np.testing.assert_allclose(mine, ref, rtol=1e-3, atol=1e-6 * ref.max())


def test_negatives_are_clipped_not_normalised():
    # A narrow-band cyan-green spectrum lies outside the sRGB gamut (R < 0).
    spec = np.zeros(31)
    spec[WAVELENGTHS_31 == 500] = 1000.0
    rgb = hdr_rgb(spec[None, None, :], WAVELENGTHS_31)[0, 0]
    raw = spectra_to_XYZ(spec, WAVELENGTHS_31) @ XYZ_TO_SRGB.T
    assert raw[0] < 0 and rgb[0] == 0
    np.testing.assert_allclose(rgb[1:], raw[1:], rtol=1e-5)
    assert rgb.max() > 1  # no normalisation


def test_hdr_rgb_accepts_a_cube_and_checks_input():
    data = np.full((2, 2, 31), 5.0, np.float32)
    rgb = hdr_rgb(SpectralCube(data, WAVELENGTHS_31))
    assert rgb.dtype == np.float32 and rgb.shape == (2, 2, 3)
    np.testing.assert_allclose(luminance(rgb), 5.0, rtol=1e-4)
    data[0, 0, 3] = np.nan
    with pytest.raises(InputError, match="NaN"):
        hdr_rgb(data, WAVELENGTHS_31)
    with pytest.raises(InputError, match="bands"):
        hdr_rgb(np.ones((2, 2, 30)), WAVELENGTHS_31)
    with pytest.raises(InputError, match="outside the CIE"):
        hdr_rgb(np.ones((1, 1, 2)), [500.0, 1000.0])


def test_hdr_exr_is_half_and_unnormalised(tmp_path):
    radiance = _colorchecker_under_d65().reshape(4, 6, 31) * 30.0  # bright, Y ≫ 1
    rgb = hdr_rgb(radiance, WAVELENGTHS_31)
    p = write_exr_rgb(tmp_path / "hdr_rgb.exr", rgb)
    f = OpenEXR.File(str(p), separate_channels=True)
    assert {c.pixels.dtype for c in f.channels().values()} == {np.dtype(np.float16)}
    back = read_exr(p)
    assert back.channels == ["R", "G", "B"]
    assert back.data.max() > 100
    np.testing.assert_allclose(back.data, rgb, rtol=2 ** -10, atol=1e-4)


def test_ldr_rule_and_encoding():
    rng = np.random.default_rng(0)
    hdr = (rng.random((50, 40, 3)) ** 3 * 20).astype(np.float32)
    ldr, exposure = ldr_rgb(hdr)
    assert ldr.dtype == np.uint8 and ldr.shape == hdr.shape
    y = luminance(hdr)
    assert exposure == pytest.approx(0.18 / np.exp(np.log(y[y > 0]).mean()), rel=1e-6)
    assert exposure == ldr_exposure(hdr)
    ref = colour.cctf_encoding(np.clip(hdr * exposure, 0, 1), function="sRGB")
    np.testing.assert_array_equal(ldr, np.rint(ref * 255).astype(np.uint8))
    # A directly visible lamp 10 000x brighter than the scene must not black out
    # the rest: the diffuse part keeps (nearly) the exposure it had without it.
    scene = np.full((40, 40, 3), 0.5, np.float32) * rng.uniform(0.2, 1.0, (40, 40, 1)).astype(np.float32)
    _, e_scene = ldr_rgb(scene)
    lit = scene.copy()
    lit[:4, :4] = 5000.0
    ldr_lit, e_lit = ldr_rgb(lit)
    assert 0.5 < e_lit / e_scene <= 1.0
    assert (ldr_lit[:4, :4] == 255).all()
    assert np.median(ldr_lit[4:]) > 60


def test_ldr_given_exposure_and_edge_cases():
    hdr = np.full((2, 2, 3), 0.5, np.float32)
    ldr, e = ldr_rgb(hdr, exposure=2.0)
    assert e == 2.0 and (ldr == 255).all()
    ldr, e = ldr_rgb(np.zeros((2, 2, 3), np.float32))
    assert e == 1.0 and (ldr == 0).all()
    # 18 % grey at exposure 1 encodes to sRGB 118.
    assert ldr_rgb(np.full((1, 1, 3), 0.18), exposure=1.0)[0][0, 0, 0] == 118
    with pytest.raises(InputError, match="exposure"):
        ldr_rgb(hdr, exposure=0)
    with pytest.raises(InputError, match="NaN"):
        ldr_rgb(np.full((1, 1, 3), np.nan))


def test_hdr_rgb_on_band_major_views_matches():
    rng = np.random.default_rng(3)
    data = rng.random((5, 7, 31)) * 10
    want = hdr_rgb(data, WAVELENGTHS_31)
    bil = np.ascontiguousarray(data.transpose(0, 2, 1).astype(">f4")).transpose(0, 2, 1)
    np.testing.assert_allclose(hdr_rgb(bil, WAVELENGTHS_31), want, rtol=1e-5)
