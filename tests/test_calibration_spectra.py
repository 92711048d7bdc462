"""Audit of radiometric calibration against independent references (exact integrals, SPy files)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mehs.calibration.spectra import Spectrum, band_average, load_spectrum
from mehs.errors import MehsError


def _gaussian_band_exact(wl, v, centres, fwhm):
    """Gaussian band average of the linearly interpolated table on a fine grid, over ±8σ
    (the response beyond is below 1e-14 of it) or the table's range."""
    out = []
    for c, f in zip(centres, fwhm):
        s = f / (2 * np.sqrt(2 * np.log(2)))
        x = np.linspace(max(wl[0], c - 8 * s), min(wl[-1], c + 8 * s), 400001)
        w = np.exp(-0.5 * ((x - c) / s) ** 2)
        out.append(np.sum(w * np.interp(x, wl, v)) / np.sum(w))
    return np.array(out)


def test_band_average_of_a_line_spectrum_matches_the_exact_integral():
    # CIE FL11 (tri-band fluorescent, 5 nm table): the old sum on a 0.5 nm grid offset
    # from the table's nodes was 0.70 % off at 528 nm, next to the 545 nm line
    import colour

    from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS

    sd = colour.SDS_ILLUMINANTS["FL11"]
    sp = Spectrum(np.asarray(sd.wavelengths, float), np.asarray(sd.values, float), "FL11")
    c = SPECIM_IQ_WAVELENGTHS[(SPECIM_IQ_WAVELENGTHS > 390) & (SPECIM_IQ_WAVELENGTHS < 770)]
    fw = np.full(c.size, 7.0)
    got = band_average(sp, c, fw)
    ref = _gaussian_band_exact(sp.wavelengths, sp.values, c, fw)
    assert np.max(np.abs(got / ref - 1)) < 1e-3


def test_band_average_keeps_a_line_beyond_three_sigma():
    # a 1 nm line 4σ from a 7 nm band's centre, 200× the continuum: the Gaussian's tail
    # there weighs it by e^-8; averaging over ±3σ only dropped it (0.4 % low)
    s = 7.0 / (2 * np.sqrt(2 * np.log(2)))
    wl = np.arange(400.0, 700.01, 0.5)
    v = np.ones_like(wl)
    line = np.argmin(np.abs(wl - (550.0 + 4 * s)))
    v[line] = 200.0
    sp = Spectrum(wl, v, "continuum + line")
    got = band_average(sp, np.array([550.0]), np.array([7.0]))
    ref = _gaussian_band_exact(wl, v, [550.0], [7.0])
    assert ref[0] > 1.003                                   # the line does count
    assert got[0] == pytest.approx(ref[0], rel=2e-5)


def test_spectrum_file_with_space_aligned_columns_is_read(tmp_path):
    # spectrometer exports pad columns with runs of spaces; the sniffer gives up on them
    p = tmp_path / "panel.txt"
    p.write_text("  400   0.90\n  500   0.95\n 600  0.97\n")
    s = load_spectrum(p)
    np.testing.assert_array_equal(s.wavelengths, [400, 500, 600])
    np.testing.assert_array_equal(s.values, [0.90, 0.95, 0.97])


@pytest.mark.parametrize("unc", ["2.5", "nan", "-0.01"])
def test_uncertainty_column_not_a_fraction_is_refused(tmp_path, unc):
    p = tmp_path / "cert.csv"
    p.write_text(f"nm,L,U\n400,1.0,{unc}\n500,2.0,0.01\n")
    with pytest.raises(MehsError, match="fraction 0..1") as e:
        load_spectrum(p)
    assert "cert.csv" in str(e.value)


def test_envi_spectral_library_is_read(tmp_path):
    from spectral.io.envi import SpectralLibrary

    wl = np.arange(350.0, 1101.0, 1.0)
    rho = 0.95 + 0.04 * np.sin(wl / 50)
    SpectralLibrary(rho[None].astype(np.float32),
                    {"wavelength": (wl / 1000).tolist(), "wavelength units": "Micrometers",
                     "spectra names": ["panel"]}, None).save(str(tmp_path / "panel"))
    for f in ("panel.sli", "panel.hdr"):
        s = load_spectrum(tmp_path / f)
        np.testing.assert_allclose(s.wavelengths, wl)
        np.testing.assert_allclose(s.values, rho, atol=1e-6)
    SpectralLibrary(np.stack([rho, rho / 2]).astype(np.float32),
                    {"wavelength": wl.tolist(), "spectra names": ["a", "b"]},
                    None).save(str(tmp_path / "two"))
    with pytest.raises(MehsError, match="2 spectra"):
        load_spectrum(tmp_path / "two.sli")


def test_envi_cube_spectrum_is_still_the_pixel_mean(tmp_path):
    from mehs.cube import SpectralCube
    from mehs.io.envi_write import write_envi

    wl = np.arange(400.0, 701.0, 10.0)
    data = np.stack([np.full((2, 3, wl.size), 1.0), np.full((2, 3, wl.size), 3.0)]).reshape(4, 3, -1)
    write_envi(tmp_path / "c.hdr", SpectralCube(data.astype(np.float32), wl))
    s = load_spectrum(tmp_path / "c.hdr")
    np.testing.assert_allclose(s.values, 2.0)


def test_truth_accuracy_resamples_the_truth_like_the_build(tmp_path):
    # a dataset built with --resample linear holds the truth's *linear* 31-band values;
    # comparing them with a Gaussian-resampled truth reported a 27 % p95 error where there is none
    from mehs.calibration.accuracy import dataset_truth_accuracy
    from mehs.capture.scene import SPECIM_IQ_FWHM, SPECIM_IQ_WAVELENGTHS
    from mehs.cube import SpectralCube
    from mehs.dataset.scene_build import to_31_bands
    from mehs.io.envi_write import write_envi

    wl = SPECIM_IQ_WAVELENGTHS
    spec = 1.0 + 4.0 * np.exp(-0.5 * ((wl - 545.0) / 2.0) ** 2)     # a narrow line
    truth = SpectralCube(np.broadcast_to(spec, (4, 5, wl.size)).astype(np.float32), wl,
                         fwhm=SPECIM_IQ_FWHM, units="W sr-1 m-2 nm-1")
    cap = tmp_path / "cap"
    write_envi(cap / "truth" / "radiance.hdr", truth)
    (cap / "scene.json").write_text(json.dumps({"truth": "truth/radiance.hdr"}))
    ds = tmp_path / "ds"
    write_envi(ds / "s" / "hs.hdr", to_31_bands(truth, method="linear"))
    (ds / "manifest.json").write_text(json.dumps({
        "format": "mehs-dataset/1", "radiance_unit": "W sr-1 m-2 nm-1", "splits": {},
        "scenes": [{"id": "s", "files": {"hs": "s/hs.hdr"}, "sha256": {},
                    "quality": {"radiance_scale": 1.0},
                    "provenance": {"params": {"resample": "linear", "fwhm": 10.0}}}]}))
    acc = dataset_truth_accuracy(ds, {"s": cap})["s"]
    assert acc["rel_error_p95"] < 1e-5 and acc["sam_median_deg"] < 1e-2


def test_wavelength_calibration_in_micrometres_is_refused(tmp_path):
    from mehs.capture.spectral_cal import read_calibration

    p = tmp_path / "wl.txt"
    p.write_text("0.4005 0.4025 0.4045\n")
    with pytest.raises(MehsError, match="does not look like nm") as e:
        read_calibration(p)
    assert "wl.txt" in str(e.value)


def test_coarse_lamp_certificate_is_interpolated_as_a_smooth_source():
    """A NIST FEL-style certificate (10-300 nm steps) of a 2856 K lamp: straight lines
    between its points were 4-5 % under the curve in the NIR bands."""
    from mehs.calibration.spectra import Spectrum, band_average

    def planck(nm, t=2856.0):
        lam = nm * 1e-9
        return lam ** -5 / np.expm1(1.4388e-2 / (lam * t))

    wl = np.array([250, 260, 270, 280, 290, 300, 310, 320, 330, 340, 350, 400, 450, 500, 555,
                   600, 654.6, 700, 800, 900, 1050, 1150, 1200, 1300, 1540, 1600, 1700, 2000,
                   2100, 2300, 2400, 2500.0])
    centres = np.linspace(400.0, 1000.0, 61)
    got = band_average(Spectrum(wl, planck(wl), "FEL"), centres, 7.0)
    sig = 7.0 / (2 * np.sqrt(2 * np.log(2)))
    o = np.linspace(-3, 3, 2001)
    w = np.exp(-0.5 * o * o)
    ref = np.array([(planck(c + sig * o) * w).sum() / w.sum() for c in centres])
    assert np.abs(got / ref - 1).max() < 0.002


def test_truth_accuracy_leaves_out_the_pixels_a_moving_scene_changed(tmp_path):
    # a moving scene's truth is its first exposure; where later exposures differ there is
    # no single truth, and the CLI / demo write truth/moved_mask.png to say where
    import cv2

    from mehs.calibration.accuracy import dataset_truth_accuracy
    from mehs.capture.scene import SPECIM_IQ_FWHM, SPECIM_IQ_WAVELENGTHS
    from mehs.cube import SpectralCube
    from mehs.dataset.scene_build import to_31_bands
    from mehs.io.envi_write import write_envi

    wl = SPECIM_IQ_WAVELENGTHS
    data = np.full((4, 5, wl.size), 2.0, np.float32)
    truth = SpectralCube(data, wl, fwhm=SPECIM_IQ_FWHM, units="W sr-1 m-2 nm-1")
    cap = tmp_path / "cap"
    write_envi(cap / "truth" / "radiance.hdr", truth)
    built = to_31_bands(truth)
    hs = np.array(built.data)
    hs[:, :3] *= 3.0                                   # the cloud moved over three columns
    ds = tmp_path / "ds"
    write_envi(ds / "s" / "hs.hdr", SpectralCube(hs, built.wavelengths, units=built.units))
    (ds / "manifest.json").write_text(json.dumps({
        "format": "mehs-dataset/1", "radiance_unit": "W sr-1 m-2 nm-1", "splits": {},
        "scenes": [{"id": "s", "files": {"hs": "s/hs.hdr"}, "sha256": {},
                    "quality": {"radiance_scale": 1.0}, "provenance": {"params": {}}}]}))
    (cap / "scene.json").write_text(json.dumps({"truth": "truth/radiance.hdr"}))
    assert dataset_truth_accuracy(ds, {"s": cap})["s"]["rel_error_median"] > 0.1
    moved = np.zeros((4, 5), np.uint8)
    moved[:, :3] = 255
    cv2.imwrite(str(cap / "truth" / "moved_mask.png"), moved)
    (cap / "scene.json").write_text(json.dumps({"truth": "truth/radiance.hdr",
                                                "truth_moved_mask": "truth/moved_mask.png"}))
    acc = dataset_truth_accuracy(ds, {"s": cap})["s"]
    assert acc["rel_error_p95"] < 1e-5 and acc["pixels"] == 8
