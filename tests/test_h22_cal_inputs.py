"""Certificates, calibration files and mismatches (audit h22).

Independent truths: Planck's law integrated over each Gaussian band on a dense grid
(numpy, not mehs), colour-science's interpolation of the same table, SI prefixes
(1 W·cm⁻² = 10⁴ W·m⁻², 1 µm⁻¹ = 10⁻³ nm⁻¹), and the simulator's responsivity.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from mehs.calibration import Calibration, calibrate_source_absolute, load_spectrum
from mehs.calibration.targets import sphere_radiance
from mehs.cli import main
from mehs.errors import FormatError, InputError

N = 16


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene
    from mehs.calibration.targets import make_target_scene
    from mehs.synthesis.bracket import load_bracket

    tmp = tmp_path_factory.mktemp("h22cal")
    sim = simulate_bracket(make_target_scene("sphere", N, N), SensorModel(seed=3),
                           (40.8, 81.5, 163.0), seed=1)
    write_simulated_scene(sim, tmp / "sphere")
    return {"dir": tmp / "sphere", "bracket": load_bracket(tmp / "sphere"),
            "truth": sim.truth_dn_per_ms, "tmp": tmp}


def _cert(path, step, header, factor=1.0, lo=350.0, hi=1100.0):
    g = np.arange(lo, hi + 1e-9, step)
    rows = [f"{w:.1f},{v * factor:.9e}" for w, v in zip(g, sphere_radiance(g))]
    path.write_text("\n".join([*header, *rows]) + "\n", encoding="utf-8")
    return path


@pytest.mark.parametrize("header,factor", [
    (["# sphere radiance", "wavelength_nm,radiance W/(cm2 sr nm)"], 1e-4),
    (["Wavelength (nm); Spectral radiance (µW cm⁻² sr⁻¹ nm⁻¹)"], 1e2),
    (["# units: mW m-2 sr-1 nm-1", "nm,L"], 1e3),
    (["wavelength_nm,radiance_W/(m^2 sr um)"], 1e3),
    (["# Labsphere 1000 W QTH lamp, certificate 12-345", "nm,W sr-1 m-2 nm-1"], 1.0),
])
def test_certificate_units_in_the_header_are_converted(sphere, tmp_path, header, factor):
    ref = calibrate_source_absolute(sphere["bracket"],
                                    load_spectrum(_cert(tmp_path / "si.csv", 5.0, [])))
    cal = calibrate_source_absolute(sphere["bracket"],
                                    load_spectrum(_cert(tmp_path / "c.csv", 5.0, header, factor)))
    np.testing.assert_allclose(cal.responsivity, ref.responsivity, rtol=1e-6)
    assert cal.parameters["source_unit"]["from"] == "header"
    assert ref.parameters["source_unit"]["from"] == "assumed"


def test_irradiance_certificate_and_ambiguous_units_are_refused(sphere, tmp_path, capsys):
    fel = _cert(tmp_path / "fel.csv", 50.0, ["# FEL lamp F-123 at 50 cm", "nm,E (W cm-2 nm-1)"])
    with pytest.raises(InputError, match="irradiance"):
        calibrate_source_absolute(sphere["bracket"], load_spectrum(fel))
    two = _cert(tmp_path / "two.csv", 5.0, ["# W m-2 sr-1 nm-1", "nm,L (uW cm-2 sr-1 nm-1)"])
    with pytest.raises(InputError, match="more than one unit"):
        calibrate_source_absolute(sphere["bracket"], load_spectrum(two))
    # the option decides; the CLI states what it did
    out = tmp_path / "c.json"
    bare = _cert(tmp_path / "bare.csv", 5.0, ["nm,L"], 1e2)
    assert main(["calibrate", str(sphere["dir"]), "--source", str(bare), "--source-unit",
                 "uW cm-2 sr-1 nm-1", "--out", str(out)]) == 0
    assert "x 0.01 to W sr-1 m-2 nm-1" in capsys.readouterr().out
    cal = Calibration.load(out)
    assert abs(np.median(cal.responsivity / sphere["truth"][None]) - 1) < 0.005
    assert main(["calibrate", str(sphere["dir"]), "--source", str(_cert(tmp_path / "s.csv", 5, [])),
                 "--out", str(out), "--force"]) == 0
    assert "unit not stated" in capsys.readouterr().out


def _planck_bands(wl, fw):
    """Planck (the sphere's) averaged over each Gaussian band, on a 0.01 nm grid."""
    x = np.arange(300.0, 1150.0, 0.01)
    lx = sphere_radiance(x)
    out = np.empty(wl.size)
    for i, (c, f) in enumerate(zip(wl, fw)):
        sel = np.abs(x - c) < 6 * f
        w = np.exp(-0.5 * ((x[sel] - c) / (f / 2.3548200450309493)) ** 2)
        out[i] = np.sum(w * lx[sel]) / np.sum(w)
    return out


@pytest.mark.parametrize("step", [5.0, 10.0, 50.0])
def test_certificate_interpolation_of_a_smooth_source(sphere, tmp_path, step):
    """Band values from a 5/10/50 nm certificate against the exact band integral, and
    against colour-science's interpolation of the same table (Sprague / spline)."""
    import colour

    br = sphere["bracket"]
    wl, fw = br.wavelengths, np.asarray(br.exposures[0].fwhm, dtype=np.float64)
    lo = 250.0 if step == 50 else 350.0
    cert = _cert(tmp_path / "c.csv", step, ["nm,radiance (W sr-1 m-2 nm-1)"], lo=lo)
    cal = calibrate_source_absolute(br, load_spectrum(cert))
    got = np.asarray(cal.parameters["reference_band_values"])
    exact = _planck_bands(wl, fw)
    err = np.max(np.abs(got / exact - 1))
    g = np.arange(lo, 1100.0 + 1e-9, step)
    sd = colour.SpectralDistribution(dict(zip(g, sphere_radiance(g))))
    sdi = sd.copy().interpolate(colour.SpectralShape(lo, 1100, 0.5))
    col = np.max(np.abs(np.interp(wl, sdi.wavelengths, sdi.values) / sphere_radiance(wl) - 1))
    print(f"{step:g} nm certificate: mehs band values max |err| {err:.2e}; colour-science "
          f"interpolation {col:.2e}")
    assert err < max(3 * col, 5e-4)


def test_band_integral_beats_point_sampling_even_for_a_smooth_source():
    """Guard: the band average of a 3000 K source differs from its value at the centre by
    up to 0.1 % at 3-7 nm FWHM; mehs's band values are the integral (exact to 1e-5)."""
    from mehs.calibration.spectra import Spectrum, band_average
    from mehs.capture.scene import SPECIM_IQ_FWHM, SPECIM_IQ_WAVELENGTHS

    g = np.arange(350.0, 1100.0 + 1e-9, 1.0)
    spec = Spectrum(g, sphere_radiance(g), "1 nm table")
    exact = _planck_bands(SPECIM_IQ_WAVELENGTHS, SPECIM_IQ_FWHM)
    got = band_average(spec, SPECIM_IQ_WAVELENGTHS, SPECIM_IQ_FWHM)
    point = sphere_radiance(SPECIM_IQ_WAVELENGTHS)
    assert np.max(np.abs(point / exact - 1)) > 5e-4
    assert np.max(np.abs(got / exact - 1)) < 1e-4


def test_certificate_that_stops_short_is_refused_not_extrapolated(sphere, tmp_path):
    """Guard: a 50 nm FEL-style table ending at 900 nm does not calibrate 1000 nm bands."""
    cert = _cert(tmp_path / "c.csv", 50.0, [], lo=250.0, hi=900.0)
    with pytest.raises(InputError, match=r"covers 250..900 nm"):
        calibrate_source_absolute(sphere["bracket"], load_spectrum(cert))
    cal = calibrate_source_absolute(sphere["bracket"], load_spectrum(cert), partial=True)
    assert cal.calibrated_wavelengths[-1] + cal.fwhm[cal.bands[-1]] <= 900.0


@pytest.fixture(scope="module")
def saved(sphere):
    cert = sphere["tmp"] / "cert.csv"
    _cert(cert, 5.0, [])
    cal = calibrate_source_absolute(sphere["bracket"], load_spectrum(cert))
    return cal, json.loads(json.dumps(cal.to_dict()))


@pytest.mark.parametrize("edit,match", [
    (lambda d: d["uncertainty"].__setitem__(3, float("nan")), "uncertainty is NaN"),
    (lambda d: d["uncertainty"].__setitem__(3, -0.01), "uncertainty is NaN, infinite or negative"),
    (lambda d: d.pop("camera"), "lacks camera"),
    (lambda d: d.pop("unit"), "lacks unit"),
    (lambda d: d["camera"].pop("samples"), "no 'samples'"),
])
def test_hand_edited_calibration_file_is_refused_by_name(saved, tmp_path, edit, match):
    d = json.loads(json.dumps(saved[1]))
    edit(d)
    p = tmp_path / "edited.json"
    p.write_text(json.dumps(d))
    with pytest.raises(FormatError, match=match) as ei:
        Calibration.load(p)
    assert str(p) in str(ei.value)


def test_one_responsivity_per_band_is_refused_on_another_width(sphere, tmp_path):
    cert = load_spectrum(_cert(tmp_path / "c.csv", 5.0, []))
    cal = calibrate_source_absolute(sphere["bracket"], cert, per_column=False)
    cal.check_compatible(cal.wavelengths, N)
    with pytest.raises(InputError, match=f"made on {N} spatial columns, the data have {N // 2}"):
        cal.check_compatible(cal.wavelengths, N // 2)
    # guard: reversed / unsorted band order is another band set
    with pytest.raises(InputError, match="other wavelengths"):
        cal.check_compatible(cal.wavelengths[::-1], N)
