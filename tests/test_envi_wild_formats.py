"""ENVI files as other instruments and tools write them, read by mehs and by SPy.

Each file is written here in the vendor's layout (header text and binary), then
read with :func:`mehs.io.envi.read_envi` and with ``spectral.envi.open``; the data
must agree in (lines, samples, bands) orientation, wavelengths in nm.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import spectral.io.envi as spy_envi

from mehs.errors import FormatError
from mehs.io.envi import read_envi

L, S, B = 3, 4, 5
WL_NM = np.array([450.0, 550.0, 650.0, 750.0, 850.0])


def _cube(dtype=np.uint16, seed=0):
    return np.random.default_rng(seed).integers(0, 4000, (L, S, B)).astype(dtype)


def _write(tmp_path, stem, header, file_order, dtype, ext, prefix=b""):
    hp = tmp_path / f"{stem}.hdr"
    hp.write_text(header)
    dp = tmp_path / f"{stem}{ext}"
    dp.write_bytes(prefix + np.ascontiguousarray(file_order, dtype=dtype).tobytes())
    return hp, dp


def _spy(hp, dp):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        img = spy_envi.open(str(hp), str(dp))
        return np.asarray(img.load(dtype=np.float64)), img


def _wl(values):
    return ", ".join(f"{v:g}" for v in values)


def test_hyspex_header_finds_its_dot_hyspex_data(tmp_path):
    # HySpex cameras write x.hyspex (own binary header, skipped by 'header offset')
    # beside x.hdr; reading the header must find the .hyspex data file.
    cube = _cube()
    binary_header = b"HYSPEX\0\0" + bytes(1992)
    header = ("ENVI\ndescription = {HySpex VNIR-1800}\n"
              f"samples = {S}\nlines = {L}\nbands = {B}\nheader offset = {len(binary_header)}\n"
              "file type = ENVI Standard\ndata type = 12\ninterleave = bil\nbyte order = 0\n"
              "default bands = {4, 2, 1}\nwavelength units = nm\n"
              f"wavelength = {{{_wl(WL_NM)}}}\nfwhm = {{{_wl([3.6] * B)}}}\n")
    hp, dp = _write(tmp_path, "scan_VNIR_1800_raw", header, cube.transpose(0, 2, 1), "<u2",
                    ".hyspex", prefix=binary_header)
    c = read_envi(hp)
    ref, _ = _spy(hp, dp)
    assert c.data.shape == (L, S, B)
    np.testing.assert_array_equal(np.asarray(c.data), ref)
    np.testing.assert_array_equal(np.asarray(c.data), cube)
    assert c.default_bands == (3, 1, 0)
    np.testing.assert_allclose(c.wavelengths, WL_NM)


@pytest.mark.parametrize("units_line", ["", "wavelength units = Unknown\n"])
def test_micrometre_centres_without_units_are_converted(tmp_path, units_line):
    # ENVI Classic / AVIRIS-style headers list centres in µm; without (known) units
    # mehs read 0.45..0.85 as nanometres (X-rays), silently when the key was absent.
    cube = _cube(np.int16)
    header = (f"ENVI\nsamples = {S}\nlines = {L}\nbands = {B}\ndata type = 2\n"
              "interleave = bsq\nbyte order = 1\nheader offset = 128\n" + units_line
              + f"wavelength = {{{_wl(WL_NM / 1000)}}}\nfwhm = {{{_wl([0.01] * B)}}}\n")
    hp, dp = _write(tmp_path, "cup", header, cube.transpose(2, 0, 1), ">i2", ".img",
                    prefix=bytes(128))
    with pytest.warns(UserWarning, match="micrometres"):
        c = read_envi(hp)
    ref, img = _spy(hp, dp)
    np.testing.assert_allclose(c.wavelengths, np.asarray(img.bands.centers) * 1000)
    np.testing.assert_allclose(c.fwhm, 10.0)
    np.testing.assert_array_equal(np.asarray(c.data), ref)


def test_band_index_wavelengths_are_not_taken_for_micrometres(tmp_path):
    cube = _cube()
    header = (f"ENVI\nsamples = {S}\nlines = {L}\nbands = {B}\ndata type = 12\n"
              "interleave = bip\nbyte order = 0\nwavelength units = Index\n"
              "wavelength = {1, 2, 3, 4, 5}\n")
    hp, _ = _write(tmp_path, "idx", header, cube, "<u2", ".img")
    with pytest.warns(UserWarning, match="assuming nanometres"):
        c = read_envi(hp)
    np.testing.assert_array_equal(c.wavelengths, [1, 2, 3, 4, 5])


@pytest.mark.parametrize("unit,factor", [("Nanometres", 1.0), ("micrometres", 1000.0)])
def test_british_spelling_of_units(tmp_path, unit, factor):
    cube = _cube()
    header = (f"ENVI\nsamples = {S}\nlines = {L}\nbands = {B}\ndata type = 12\n"
              f"interleave = bip\nbyte order = 0\nwavelength units = {unit}\n"
              f"wavelength = {{{_wl(WL_NM / factor)}}}\n")
    hp, _ = _write(tmp_path, "gb", header, cube, "<u2", ".img")
    np.testing.assert_allclose(read_envi(hp).wavelengths, WL_NM)


def test_spectral_library_is_named_not_a_missing_data_file(tmp_path):
    header = ("ENVI\ndescription = {lib}\nsamples = 5\nlines = 3\nbands = 1\n"
              "header offset = 0\nfile type = ENVI Spectral Library\ndata type = 4\n"
              "interleave = bsq\nbyte order = 0\nwavelength units = Nanometers\n"
              f"wavelength = {{{_wl(WL_NM)}}}\nspectra names = {{a, b, c}}\n")
    hp, dp = _write(tmp_path, "lib", header, np.ones((3, 5)), "<f4", ".sli")
    for path in (hp, dp):
        with pytest.raises(FormatError, match=r"spectral library \(3 spectra of 5 wave") as ei:
            read_envi(path)
        assert "lib.hdr" in str(ei.value)


# ---- layouts that already read right: kept as regression checks against SPy


def test_headwall_bip_nonzero_offset_no_extension(tmp_path):
    cube = _cube()
    header = ("ENVI\ndescription = {Headwall Hyperspec}\n"
              f"samples = {S}\nlines = {L}\nbands = {B}\nheader offset = 16384\n"
              "file type = ENVI Standard\ndata type = 12\ninterleave = bip\nbyte order = 0\n"
              f"wavelength units = Nanometers\nwavelength = {{\n{_wl(WL_NM)}\n}}\n")
    hp, dp = _write(tmp_path, "raw_0", header, cube, "<u2", "", prefix=bytes(16384))
    c = read_envi(hp)
    ref, _ = _spy(hp, dp)
    np.testing.assert_array_equal(np.asarray(c.data), ref)
    assert c.units == "DN"


def test_envi_classic_float64_big_endian_gains_kept_not_applied(tmp_path):
    # ENVI, SPy and GDAL all leave 'data gain/offset values' unapplied on reading:
    # they are calibration metadata for ENVI's radiometric tools.
    f = np.random.default_rng(1).random((L, S, B))
    header = ("ENVI\ndescription = {\n  Created by ENVI Classic,\n  a = b}\n"
              f"Samples = {S}\nLines   = {L}\nBands   = {B}\nHeader Offset = 0\n"
              "File Type = ENVI Standard\nData Type = 5\nInterleave = BSQ\nByte Order = 1\n"
              "map info = {UTM, 1.0, 1.0, 500000.0, 4000000.0, 30.0, 30.0, 13, North, "
              "WGS-84, units=Meters}\nWavelength Units = Micrometers\n"
              f"wavelength = {{{_wl(WL_NM / 1000)}}}\n"
              f"data gain values = {{{_wl([2.0] * B)}}}\n"
              f"data offset values = {{{_wl([1.0] * B)}}}\n")
    hp, dp = _write(tmp_path, "classic", header, f.transpose(2, 0, 1), ">f8", ".img")
    c = read_envi(hp)
    ref, _ = _spy(hp, dp)
    assert c.data.dtype == np.float64
    np.testing.assert_array_equal(np.asarray(c.data), f)
    np.testing.assert_allclose(np.asarray(c.data), ref, rtol=1e-6)
    np.testing.assert_allclose(c.wavelengths, WL_NM)
    assert c.metadata["data gain values"] == ["2"] * B


def test_resonon_reflectance_scale_factor_as_spy(tmp_path):
    cube = _cube()
    header = (f"ENVI\ninterleave = bip\ndata type = 12\nsamples = {S}\nlines = {L}\n"
              f"bands = {B}\nbyte order = 0\nheader offset = 0\n"
              "reflectance scale factor = 10000\nwavelength units = nm\n"
              f"wavelength = {{{_wl(WL_NM)}}}\n")
    hp, dp = _write(tmp_path, "resonon", header, cube, "<u2", ".bip")
    c = read_envi(hp)
    _, img = _spy(hp, dp)
    np.testing.assert_allclose(np.asarray(c.data), np.asarray(img.load()), rtol=1e-6)
    assert c.units == "reflectance"


def test_solar_irradiance_follows_its_bands_when_sorted(tmp_path):
    # ENVI radiometric calibration writes 'solar irradiance = {…}' (one value per band);
    # sorting unsorted wavelengths must move it with the bands, as bbl and band names.
    cube = _cube()
    header = (f"ENVI\nsamples = {S}\nlines = {L}\nbands = {B}\ndata type = 12\n"
              "interleave = bip\nbyte order = 0\nwavelength units = Nanometers\n"
              "wavelength = {850, 750, 650, 550, 450}\n"
              "solar irradiance = {1070, 1280, 1530, 1850, 1940}\n"
              "band names = {NIR2, NIR1, R, G, B}\n")
    hp, _ = _write(tmp_path, "cal", header, cube, "<u2", ".img")
    with pytest.warns(UserWarning, match="not sorted"):
        c = read_envi(hp)
    np.testing.assert_array_equal(np.asarray(c.data), cube[..., ::-1])
    assert c.metadata["band names"] == ["B", "G", "R", "NIR1", "NIR2"]
    assert c.metadata["solar irradiance"] == ["1940", "1850", "1530", "1280", "1070"]
