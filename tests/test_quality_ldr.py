"""Audit of the LDR-RGB against outside truth: colour-science's sRGB OETF/EOTF, 8-bit rounding,
the documented exposure rule, and the documented decoding (docs/ssr.md item 4) back to the HDR."""

import numpy as np
import pytest

from mehs.errors import InputError
from mehs.rgb import WAVELENGTHS_31, ldr_exposure, ldr_rgb


def _colorchecker_cube(lines=24, samples=36):
    """ColorChecker reflectances under D65 (colour-science's measured spectra) on the 31 bands,
    a 4 × 6 patch layout stretched over the image, brightness rising left to right and a
    100× "lamp" block in the top-left corner (asymmetric, HDR)."""
    import colour

    cc = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    d65 = colour.SDS_ILLUMINANTS["D65"]
    refl = np.array([[sd[w] for w in WAVELENGTHS_31] for sd in cc.values()])     # (24, 31)
    ill = np.array([d65[w] for w in WAVELENGTHS_31]) / 100.0
    r = (np.arange(lines) * 4 // lines)[:, None]
    c = (np.arange(samples) * 6 // samples)[None, :]
    cube = refl[r * 6 + c] * ill * np.linspace(0.2, 2.0, samples)[None, :, None]
    cube[:3, :4] *= 100.0
    return cube.astype(np.float32)


def _independent_rgb(cube):
    """Pseudo-HDR-RGB from colour-science's tables and sRGB matrix (paper §3.1 steps 1–3)."""
    import colour

    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    cmf = np.stack([np.interp(WAVELENGTHS_31, cmfs.wavelengths, cmfs.values[:, i])
                    for i in range(3)], axis=1)
    xyz = cube.astype(np.float64) @ cmf / cmf[:, 1].sum()
    srgb = colour.RGB_COLOURSPACES["sRGB"]
    return np.maximum(xyz @ srgb.matrix_XYZ_to_RGB.T, 0), srgb.matrix_RGB_to_XYZ[1]


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_exposure_of_an_image_with_nan_or_inf_is_refused_not_silently_metered(bad):
    hdr = np.ones((4, 5, 3), np.float32)
    hdr[1, 2, 0] = bad
    with pytest.raises(InputError, match="NaN/Inf"):
        ldr_exposure(hdr)


@pytest.mark.parametrize("key", [0.0, -0.18, np.nan, np.inf])
def test_a_non_positive_key_is_named_in_the_error(key):
    hdr = np.ones((4, 5, 3), np.float32)
    with pytest.raises(InputError, match="key"):
        ldr_exposure(hdr, key)
    with pytest.raises(InputError, match="key"):
        ldr_rgb(hdr, key=key)


def test_ldr_matches_colour_science_encoding_and_the_documented_rule():
    import colour

    from mehs.rgb import hdr_rgb

    cube = _colorchecker_cube()
    hdr = hdr_rgb(cube, WAVELENGTHS_31)
    ref, y_row = _independent_rgb(cube)
    # mehs keeps the IEC matrix to 4 digits; colour derives it from the primaries
    np.testing.assert_allclose(hdr, ref, rtol=1e-3, atol=1e-6 * ref.max())
    ldr, exposure = ldr_rgb(hdr)
    Y = ref @ y_row
    assert exposure == pytest.approx(0.18 / np.exp(np.mean(np.log(Y[Y > 0]))), rel=2e-4)
    # rint(255 · OETF(clip(exposure · RGB, 0, 1))), colour's OETF; rounding, not truncation
    expect = np.rint(255 * colour.cctf_encoding(
        np.clip(hdr.astype(np.float64) * exposure, 0, 1), function="sRGB"))
    assert np.abs(ldr.astype(int) - expect).max() <= 1     # float32 vs float64 at a .5 edge
    assert (ldr == expect).mean() > 0.999
    assert ldr[:3, :4].max(axis=2).min() == 255 and ldr.shape == hdr.shape  # the lamp clips


def test_dataset_ldr_png_decodes_back_to_the_exr_within_quantisation(tmp_path):
    """docs/ssr.md item 4: PNG → sRGB EOTF → ÷ quality.ldr_exposure gives the EXR's HDR-RGB."""
    import colour

    from mehs.cube import SpectralCube
    from mehs.dataset.build import build_from_hs
    from mehs.dataset.manifest import read_manifest
    from mehs.io.envi import write_envi
    from mehs.io.exr import read_exr
    from mehs.preview import read_png

    cube = _colorchecker_cube() * np.float32(3e4)  # past the half-float range: stored scaled
    write_envi(tmp_path / "in" / "cc.hdr", SpectralCube(cube, WAVELENGTHS_31))
    build_from_hs([tmp_path / "in"], tmp_path / "ds", workers=1, progress=False)
    s = read_manifest(tmp_path / "ds")["scenes"][0]
    q = s["quality"]
    assert q["radiance_scale"] < 1
    hdr = read_exr(tmp_path / "ds" / s["files"]["hdr_rgb"]).data[:, :, :3].astype(np.float64)
    png = read_png(tmp_path / "ds" / s["files"]["ldr_rgb"])
    assert png.dtype == np.uint8 and png.shape == hdr.shape
    e = q["ldr_exposure"]
    decoded = colour.cctf_decoding(png / 255.0, function="sRGB") / e
    # the code's interval in linear units, divided by the exposure
    lo = colour.cctf_decoding(np.maximum(png - 0.5, 0) / 255.0, function="sRGB") / e
    hi = colour.cctf_decoding(np.minimum(png + 0.5, 255) / 255.0, function="sRGB") / e
    inside = (png > 0) & (png < 255)
    tol = 2e-3 * hdr + 1e-9   # the EXR is half-float (3 decimal digits)
    assert inside.mean() > 0.5
    assert np.all(hdr[inside] >= lo[inside] - tol[inside])
    assert np.all(hdr[inside] <= hi[inside] + tol[inside])
    assert np.median(np.abs(decoded - hdr)[inside] / hdr[inside]) < 0.01
    # clipped codes are lower bounds, zero codes upper bounds
    assert np.all(hdr[png == 255] * e >= 1 - 2e-3 - 1 / 255)
    assert np.all(hdr[png == 0] * e <= colour.cctf_decoding(0.5 / 255, function="sRGB") + 1e-6)


def test_dataset_ldr_png_is_the_ldr_of_the_stored_exr_exactly(tmp_path):
    """The LDR image and its exposure follow from the dataset's own half-float EXR."""
    from mehs.cube import SpectralCube
    from mehs.dataset.build import build_from_hs
    from mehs.dataset.manifest import read_manifest
    from mehs.io.envi import write_envi
    from mehs.io.exr import read_exr
    from mehs.preview import read_png
    from mehs.rgb import ldr_rgb

    rng = np.random.default_rng(3)
    cube = (_colorchecker_cube() * rng.uniform(0.3, 3.0, (1, 1, 1)).astype(np.float32)
            * np.float32(1.37))
    write_envi(tmp_path / "in" / "cc.hdr", SpectralCube(cube, WAVELENGTHS_31))
    build_from_hs([tmp_path / "in"], tmp_path / "ds", workers=1, progress=False)
    s = read_manifest(tmp_path / "ds")["scenes"][0]
    hdr = read_exr(tmp_path / "ds" / s["files"]["hdr_rgb"]).data[:, :, :3].astype(np.float32)
    ldr, exposure = ldr_rgb(hdr)
    assert exposure == s["quality"]["ldr_exposure"]
    np.testing.assert_array_equal(ldr, read_png(tmp_path / "ds" / s["files"]["ldr_rgb"]))
