"""Tone-mapped previews and PNG helpers."""

import numpy as np
import pytest

from mehs.cube import SpectralCube
from mehs.errors import FormatError, InputError
from mehs.preview import (hs_preview, preview_rgb, read_png, tonemap, tonemap_Reinhard2002,
                          write_png)
from mehs.rgb import WAVELENGTHS_31, hdr_rgb, luminance

RNG = np.random.default_rng(11)


def _srgb_decode(u8):
    v = u8 / 255.0
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def test_reinhard_matches_the_formula():
    rgb = (RNG.random((16, 16, 3)) ** 4 * 1000).astype(np.float32)
    key, white = 0.18, 5.0
    lw = luminance(rgb.astype(np.float64))
    log_avg = np.exp(np.mean(np.log(1e-6 * lw.max() + lw)))
    l = key / log_avg * lw
    ld = l * (1 + l / white ** 2) / (1 + l)
    want = np.clip(rgb * (ld / lw)[..., None], 0, 1)
    got = _srgb_decode(tonemap_Reinhard2002(rgb, key=key, white=white))
    # 8-bit quantisation of the sRGB code is the only difference.
    np.testing.assert_allclose(got, want, atol=0.01)


def test_reinhard_default_white_keeps_the_brightest_pixel_below_clipping_in_luminance():
    rgb = np.ones((8, 8, 3), np.float32) * 0.01
    rgb[0, 0] = 1e4  # a light source 10^6 × brighter
    out = tonemap(rgb)
    assert out.dtype == np.uint8 and out.shape == (8, 8, 3)
    assert out[0, 0].tolist() == [255, 255, 255]
    assert 0 < out[4, 4, 0] < 255
    # Invariant to the overall scale (log-average normalises it).
    np.testing.assert_array_equal(tonemap(rgb * 37.0), out)


def test_tonemap_edge_cases():
    assert (tonemap(np.zeros((3, 3, 3))) == 0).all()
    with pytest.raises(InputError, match="unknown tone-mapping"):
        tonemap(np.ones((2, 2, 3)), "drago")
    with pytest.raises(InputError, match="NaN"):
        tonemap(np.full((2, 2, 3), np.inf))
    with pytest.raises(InputError, match=r"\(H, W, 3\)"):
        tonemap(np.ones((2, 2)))
    assert tonemap(np.full((2, 2, 3), 0.5), "exposure", exposure=2.0).min() == 255


def test_hs_preview_colorimetric_for_visible_cubes():
    data = RNG.random((6, 5, 31)).astype(np.float32) * 10
    cube = SpectralCube(data, WAVELENGTHS_31)
    np.testing.assert_array_equal(preview_rgb(cube), hdr_rgb(data, WAVELENGTHS_31))
    assert hs_preview(cube).shape == (6, 5, 3)


def test_hs_preview_on_a_specim_range_cube_uses_only_cmf_bands():
    wl = np.linspace(397.32, 1003.58, 204)
    data = RNG.random((4, 4, 204)).astype(np.float32)
    data[:, :, wl > 830] = np.nan  # must not be read
    rgb = preview_rgb(SpectralCube(data, wl))
    sel = wl <= 830
    np.testing.assert_allclose(rgb, hdr_rgb(data[:, :, sel], wl[sel]), rtol=1e-6)


def test_hs_preview_false_colour_outside_the_visible():
    wl = np.arange(900.0, 1700.0, 10.0)
    data = RNG.random((3, 3, wl.size)).astype(np.float32)
    cube = SpectralCube(data, wl, default_bands=(10, 5, 0))
    np.testing.assert_array_equal(preview_rgb(cube), data[:, :, [10, 5, 0]])
    assert hs_preview(cube).dtype == np.uint8


def test_png_round_trip_rgb_order_and_atomicity(tmp_path):
    img = RNG.integers(0, 256, (7, 9, 3), dtype=np.uint8)
    p = write_png(tmp_path / "a.png", img)
    np.testing.assert_array_equal(read_png(p), img)
    import cv2
    np.testing.assert_array_equal(cv2.imread(str(p))[:, :, ::-1], img)  # stored as real RGB
    gray = RNG.integers(0, 256, (4, 5), dtype=np.uint8)
    np.testing.assert_array_equal(read_png(write_png(tmp_path / "g.png", gray)), gray)
    with pytest.raises(InputError, match="uint8 or uint16"):
        write_png(tmp_path / "f.png", img.astype(np.float32))
    assert sorted(q.name for q in tmp_path.iterdir()) == ["a.png", "g.png"]
    (tmp_path / "bad.png").write_text("nope")
    with pytest.raises(FormatError, match="bad.png"):
        read_png(tmp_path / "bad.png")
    with pytest.raises(InputError, match="does not exist"):
        read_png(tmp_path / "none.png")
