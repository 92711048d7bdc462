"""Calibration inputs as labs receive them: ENVI libraries with a header offset, European
CSV certificates, a misspelt region; and the white-line calibration against the Specim IQ's
own reflectance formula on folders written byte for byte in the IQ layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mehs.calibration import calibrate_panel_relative, load_spectrum
from mehs.calibration.spectra import Spectrum
from mehs.errors import FormatError, InputError


def _library(path: Path, wl: np.ndarray, values: np.ndarray, *, offset: int = 0) -> Path:
    """A one-spectrum ENVI spectral library (ENVI's layout: ``lines`` spectra × ``samples``
    wavelengths, ``bands = 1``) whose data start ``offset`` bytes into the ``.sli``."""
    path.with_suffix(".hdr").write_text(
        "ENVI\ndescription = {panel certificate}\n"
        f"samples = {wl.size}\nlines = 1\nbands = 1\nheader offset = {offset}\n"
        "file type = ENVI Spectral Library\ndata type = 4\ninterleave = bsq\nbyte order = 0\n"
        "wavelength units = Nanometers\nspectra names = {Spectralon 99}\n"
        "wavelength = {" + ", ".join(f"{w:g}" for w in wl) + "}\n", encoding="ascii")
    path.write_bytes(b"ENVI-EMBEDDED".ljust(offset, b"\0")[:offset]
                     + values.astype("<f4").tobytes())
    return path


def test_spectral_library_with_a_header_offset_is_read_from_the_offset(tmp_path):
    # ENVI: "header offset" = bytes of embedded header before the data, in every file
    # type; SPy's envi.open ignores it for libraries (the values came out shifted)
    wl = np.arange(350.0, 1101.0, 10.0)
    rho = np.linspace(0.95, 0.99, wl.size)
    for off in (0, 64):
        s = load_spectrum(_library(tmp_path / f"panel{off}.sli", wl, rho, offset=off))
        np.testing.assert_allclose(s.values, rho, rtol=1e-6)
        np.testing.assert_array_equal(s.wavelengths, wl)


def test_truncated_spectral_library_names_the_sizes(tmp_path):
    wl = np.arange(400.0, 701.0, 10.0)
    p = _library(tmp_path / "short.sli", wl, np.full(wl.size, 0.9), offset=32)
    p.write_bytes(p.read_bytes()[:-8])
    with pytest.raises(FormatError, match="header offset 32"):
        load_spectrum(p)


@pytest.mark.parametrize("text, unc", [
    # European spectrometer export: ';' columns, decimal commas, a title and column names
    ("Labsphere SRT-99-050 certificate 12345\nWavelength (nm);Reflectance\n"
     "400;0,981\n500;0,985\n600;0,987\n700;0,988\n", None),
    ("wavelength\tradiance\tu\n400\t1,25E-03\t0,02\n500\t2,5E-03\t0,02\n"
     "600\t3,75E-03\t0,02\n700\t5E-03\t0,02\n", 0.02),
    ("Certificate of calibration\nSphere S/N 7\nnm,W/(m2 sr nm),k=1\n400,1.25e-3,0.02\n"
     "500,2.5e-3,0.02\n600,3.75e-3,0.02\n700,5e-3,0.02\n", 0.02),
])
def test_csv_certificates_with_header_blocks_and_decimal_commas(tmp_path, text, unc):
    p = tmp_path / "cert.csv"
    p.write_text(text, encoding="utf-8")
    s = load_spectrum(p)
    np.testing.assert_array_equal(s.wavelengths, [400, 500, 600, 700])
    if unc is None:
        np.testing.assert_allclose(s.values, [0.981, 0.985, 0.987, 0.988])
        assert s.uncertainty is None
    else:
        np.testing.assert_allclose(s.values, [1.25e-3, 2.5e-3, 3.75e-3, 5e-3])
        np.testing.assert_allclose(s.uncertainty, unc)


def test_text_after_the_data_is_still_an_error(tmp_path):
    p = tmp_path / "cert.csv"
    p.write_text("nm,v\n400,1.0\n500,1.1\nEnd of data\n", encoding="utf-8")
    with pytest.raises(FormatError, match="line 4 is not numbers"):
        load_spectrum(p)


# ----------------------------------------------------------- IQ-layout folders


def _iq_cube(path: Path, cube: np.ndarray, wl: np.ndarray, tint: float) -> None:
    """``cube`` (lines, samples, bands) as the IQ writes it: uint16 bil, Specim header keys."""
    lines, samples, bands = cube.shape
    path.with_suffix(".hdr").write_text(
        "ENVI\ndescription = {\nFile Imported into ENVI}\nfile type = ENVI\n\n"
        "sensor type = SPECIM IQ\nacquisition date = DATE(dd-mm-yyyy): 31-10-2019\n"
        "Start Time = UTC TIME: 19:03:36\n\n"
        f"samples = {samples}\nbands = {bands}\nlines = {lines}\n\nerrors = {{none}}\n\n"
        "interleave = bil\ndata type = 12\nheader offset = 0\nbyte order = 0\n"
        "default bands = {3, 2, 1}\nbinning = {1, 1}\n"
        f"tint = {tint:.6f}\n\nWavelength = {{\n" + ",\n".join(f"{w:.2f}" for w in wl) + "\n}\n",
        encoding="ascii")
    path.with_suffix(".raw").write_bytes(
        np.ascontiguousarray(cube.transpose(0, 2, 1)).astype("<u2").tobytes())


@pytest.fixture(scope="module")
def iq_bracket(tmp_path_factory):
    """Two IQ folders (10 and 40 ms) of a scene of known reflectance; the references have
    other line counts than the scene and than each other, as on the camera."""
    root = tmp_path_factory.mktemp("iq")
    rng = np.random.default_rng(7)
    samples, bands, lines = 12, 6, 8
    wl = np.linspace(450.0, 650.0, bands)
    rho = rng.uniform(0.05, 0.9, (lines, samples, bands))
    resp = rng.uniform(20.0, 40.0, (samples, bands))          # DN/ms of a perfect white
    folders = []
    for t, n_dark, n_white in ((10.0, 3, 5), (40.0, 2, 7)):
        cid = f"{int(t)}ms"
        cap = root / cid / "capture"
        cap.mkdir(parents=True)
        level = 64 + 0.5 * t                                   # black + dark current
        dark = np.rint(level + rng.normal(0, 0.3, (n_dark, samples, bands)))
        white = np.rint(level + 0.99 * resp * t + rng.normal(0, 0.3, (n_white, samples, bands)))
        raw = np.rint(level + rho * resp * t)
        _iq_cube(cap / cid, raw, wl, t)
        _iq_cube(cap / f"DARKREF_{cid}", dark, wl, t)
        _iq_cube(cap / f"WHITEREF_{cid}", white, wl, t)
        folders.append((root / cid, raw, dark.mean(axis=0), white.mean(axis=0), t))
    return folders


def test_white_line_calibration_reproduces_the_iq_reflectance_formula(iq_bracket):
    from mehs.synthesis.bracket import load_bracket
    from mehs.synthesis.fuse import fuse_bracket

    br = load_bracket([str(f[0]) for f in iq_bracket])
    flat = Spectrum(np.array([300.0, 1100.0]), np.array([0.99, 0.99]), "panel 0.99")
    ill = Spectrum(np.array([300.0, 1100.0]), np.array([1.0, 1.0]), "flat illuminant")
    cal = calibrate_panel_relative(br, flat, ill, region="white")
    rad = np.asarray(fuse_bracket(br, response="linear", ghosts="off", calibration=cal)
                     .radiance.data, dtype=np.float64)
    # the IQ's REFLECTANCE: (S - D)/(W - D), references averaged over their lines;
    # L = ρ·E/π with E = 1 here, so π·L is the reflectance
    raw, d, w = iq_bracket[1][1:4]                            # the longer exposure
    iq = (raw - d) / (w - d) * 0.99
    ratio = np.pi * rad / iq
    assert abs(np.median(ratio) - 1) < 1e-3 and np.percentile(np.abs(ratio - 1), 95) < 0.01


@pytest.mark.parametrize("region", ["Frame", "whites", "frame:0-3", "lines:3", "lines:-1-2"])
def test_a_misspelt_region_is_refused_before_any_work(iq_bracket, region):
    from mehs.synthesis.bracket import load_bracket

    br = load_bracket([str(f[0]) for f in iq_bracket])
    flat = Spectrum(np.array([300.0, 1100.0]), np.array([0.99, 0.99]), "panel 0.99")
    with pytest.raises(InputError, match="region must be 'white', 'frame' or 'lines:A-B'"):
        calibrate_panel_relative(br, flat, flat, region=region)


def test_a_lines_region_with_blanks_is_read(iq_bracket):
    from mehs.synthesis.bracket import load_bracket

    br = load_bracket([str(f[0]) for f in iq_bracket])
    flat = Spectrum(np.array([300.0, 1100.0]), np.array([0.99, 0.99]), "panel 0.99")
    cal = calibrate_panel_relative(br, flat, flat, region="lines: 0 - 3")
    assert cal.parameters["region"] == "lines: 0 - 3"
    with pytest.raises(InputError, match="outside the capture's 0-7"):
        calibrate_panel_relative(br, flat, flat, region="lines:2-8")
