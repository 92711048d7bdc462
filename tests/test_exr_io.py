"""OpenEXR I/O: round trips, channel order, spectral layout, bad input."""

import numpy as np
import OpenEXR
import pytest

from mehs.cube import SpectralCube
from mehs.errors import FormatError, InputError
from mehs.io.exr import (EXR_MAGIC, read_exr, read_exr_spectral, spectral_channels,
                         wavelength_channel_name, write_exr, write_exr_gray, write_exr_rgb,
                         write_exr_spectral)

RNG = np.random.default_rng(20260524)


def _pixel_types(path):
    f = OpenEXR.File(str(path), separate_channels=True)
    return {name: ch.pixels.dtype for name, ch in f.channels().items()}


def test_float_rgb_round_trip_is_exact(tmp_path):
    img = (RNG.random((13, 17, 3)) * 1e4).astype(np.float32)
    p = write_exr_rgb(tmp_path / "rgb.exr", img, half=False)
    back = read_exr(p)
    assert back.channels == ["R", "G", "B"]
    assert back.data.dtype == np.float32
    np.testing.assert_array_equal(back.data, img)
    assert set(_pixel_types(p).values()) == {np.dtype(np.float32)}


def test_half_rgb_round_trip_within_half_precision(tmp_path):
    img = (RNG.random((9, 11, 3)) * 3000 + 1e-3).astype(np.float32)
    p = write_exr_rgb(tmp_path / "rgb_half.exr", img)  # half by default
    assert set(_pixel_types(p).values()) == {np.dtype(np.float16)}
    back = read_exr(p).data
    np.testing.assert_allclose(back, img, rtol=2 ** -11)
    np.testing.assert_array_equal(back, img.astype(np.float16).astype(np.float32))


def test_gray_round_trip(tmp_path):
    img = RNG.normal(size=(6, 5)).astype(np.float32)
    back = read_exr(write_exr_gray(tmp_path / "g.exr", img))
    assert back.channels == ["Y"]
    np.testing.assert_array_equal(back.data[:, :, 0], img)


def test_channel_order_is_preserved(tmp_path):
    img = RNG.random((4, 4, 5)).astype(np.float32)
    names = ["Z", "B", "a", "R", "depth"]
    back = read_exr(write_exr(tmp_path / "o.exr", img, names))
    assert back.channels == names
    for i, n in enumerate(names):
        np.testing.assert_array_equal(back.channel(n), img[:, :, i])


def test_foreign_file_uses_conventional_order(tmp_path):
    # Written without the mehs order attribute, as another tool would.
    planes = {n: np.full((2, 3), v, np.float32) for v, n in enumerate(["A", "B", "G", "R"])}
    p = tmp_path / "foreign.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 planes).write(str(p))
    back = read_exr(p)
    assert back.channels == ["R", "G", "B", "A"]
    assert back.data[0, 0].tolist() == [3, 2, 1, 0]


def test_spectral_round_trip_keeps_wavelengths_and_data(tmp_path):
    wl = np.linspace(397.32, 1003.58, 204)
    data = RNG.random((8, 6, 204)).astype(np.float32) * 50
    cube = SpectralCube(data, wl, fwhm=np.full(204, 2.9), units="relative radiance")
    p = write_exr_spectral(tmp_path / "spec.exr", cube)
    back = read_exr_spectral(p)
    np.testing.assert_array_equal(back.wavelengths, wl)
    np.testing.assert_array_equal(back.data, data)
    np.testing.assert_array_equal(back.fwhm, cube.fwhm)
    assert back.units == "relative radiance"
    hdr = read_exr(p).header
    assert hdr["spectralLayoutVersion"] == "1.0"
    np.testing.assert_allclose(hdr["wavelengths"], wl, rtol=1e-6)


def test_spectral_channel_names_follow_fichet2021(tmp_path):
    assert wavelength_channel_name(400.0) == "S0.400nm"
    assert wavelength_channel_name(397.32) == "S0.397,32nm"
    assert wavelength_channel_name(550.5, "T") == "T.550,5nm"
    wl = np.arange(400.0, 701.0, 10.0)
    p = write_exr_spectral(tmp_path / "s31.exr", np.ones((2, 2, 31), np.float32), wl, half=True)
    names = read_exr(p).channels
    assert names[0] == "S0.400nm" and names[-1] == "S0.700nm" and len(names) == 31
    assert set(_pixel_types(p).values()) == {np.dtype(np.float16)}


def test_spectral_reader_accepts_foreign_names_and_ignores_rgb(tmp_path):
    # Fichet files from other writers: "S0.550,000000nm", units in um, an RGB preview.
    names = ["R", "G", "B", "S0.0,45um", "S0.550,000000nm", "S1.550,000000nm", "S0.650nm"]
    img = np.stack([np.full((3, 2), i, np.float32) for i in range(len(names))], axis=2)
    p = tmp_path / "foreign_spec.exr"
    OpenEXR.File({}, {n: img[:, :, i].copy() for i, n in enumerate(names)}).write(str(p))
    cube = read_exr_spectral(p)
    np.testing.assert_allclose(cube.wavelengths, [450, 550, 650])
    assert cube.data[0, 0].tolist() == [3, 4, 6]
    idx, wl = spectral_channels(["400nm", "410nm", "Y"])
    assert idx == [0, 1] and wl.tolist() == [400, 410]


def test_spectral_reflectance_uses_T_channels(tmp_path):
    cube = SpectralCube(np.full((2, 2, 3), 0.5, np.float32), [500, 600, 700], units="reflectance")
    p = write_exr_spectral(tmp_path / "r.exr", cube)
    assert read_exr(p).channels[0] == "T.500nm"
    assert read_exr_spectral(p).units == "reflectance"


def test_nan_and_inf_raise_naming_the_file(tmp_path):
    p = tmp_path / "nan.exr"
    img = np.ones((3, 3), np.float32)
    img[1, 1] = np.nan
    img[0, 0] = np.inf
    OpenEXR.File({}, {"Y": img}).write(str(p))
    with pytest.raises(InputError, match="nan.exr.*2 NaN/Inf"):
        read_exr(p)
    assert np.isnan(read_exr(p, check_finite=False).data[1, 1, 0])


def test_missing_and_non_exr_files(tmp_path):
    with pytest.raises(InputError, match="missing.exr: file does not exist"):
        read_exr(tmp_path / "missing.exr")
    bad = tmp_path / "text.exr"
    bad.write_text("not an image")
    with pytest.raises(FormatError, match="text.exr: not an OpenEXR"):
        read_exr(bad)
    trunc = tmp_path / "trunc.exr"
    good = write_exr_gray(tmp_path / "good.exr", np.ones((64, 64), np.float32))
    trunc.write_bytes(good.read_bytes()[:40])
    assert trunc.read_bytes()[:4] == EXR_MAGIC
    with pytest.raises(FormatError, match="trunc.exr"):
        read_exr(trunc)
    with pytest.raises(FormatError, match="no spectral channels"):
        read_exr_spectral(good)


def test_writer_refuses_bad_values_and_leaves_nothing(tmp_path):
    img = np.ones((4, 4, 3), np.float32)
    img[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        write_exr_rgb(tmp_path / "x.exr", img)
    with pytest.raises(InputError, match="half-float range"):
        write_exr_rgb(tmp_path / "y.exr", np.full((2, 2, 3), 1e5, np.float32), half=True)
    # finite in float64, Inf once stored as 32-bit float
    with pytest.raises(InputError, match="32-bit float range"):
        write_exr_rgb(tmp_path / "w.exr", np.full((2, 2, 3), 1e39), half=False)
    with pytest.raises(InputError, match="channel names"):
        write_exr(tmp_path / "z.exr", np.ones((2, 2, 5)))
    with pytest.raises(InputError, match="unique"):
        write_exr(tmp_path / "z.exr", np.ones((2, 2, 2)), ["A", "A"])
    assert list(tmp_path.iterdir()) == []


def test_write_is_atomic_and_overwrites(tmp_path):
    p = tmp_path / "img.exr"
    write_exr_gray(p, np.zeros((2, 2), np.float32))
    write_exr_gray(p, np.ones((2, 2), np.float32))
    assert read_exr(p).data.min() == 1
    assert [q.name for q in tmp_path.iterdir()] == ["img.exr"]
