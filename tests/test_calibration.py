"""Radiometric calibration against the simulator's truth, and its bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mehs.calibration import (UNIT_ABSOLUTE, UNIT_RELATIVE, Calibration, calibrate_panel_relative,
                              calibrate_source_absolute, load_spectrum)
from mehs.calibration.spectra import Spectrum
from mehs.calibration.targets import sphere_certificate
from mehs.cli import main
from mehs.errors import MehsError

SIZE = 24


def _capture(tmp_path, scene, name, **kw):
    rc = main(["capture", "--simulate", "--scene", scene, "--size", str(SIZE), "--out",
               str(tmp_path / name), "--no-progress", *sum(([f"--{k}", str(v)] for k, v in kw.items()), [])])
    assert rc == 0
    return tmp_path / name


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cal")
    return {"sphere": _capture(tmp, "sphere", "sphere"), "window": _capture(tmp, "window", "window"),
            "tmp": tmp}


def test_sphere_calibration_recovers_the_simulated_responsivity(captures):
    from mehs.synthesis.bracket import load_bracket

    sph = captures["sphere"]
    cert = sph / "truth" / "source_radiance.csv"
    assert cert.is_file()
    br = load_bracket(sph)
    cal = calibrate_source_absolute(br, load_spectrum(cert))
    truth = np.asarray(json.loads((sph / "scene.json").read_text())["truth_dn_per_ms_per_radiance"])
    ratio = cal.responsivity / truth[None, :]
    print(f"responsivity / truth: median {np.median(ratio):.5f}, p1-p99 "
          f"{np.percentile(ratio, 1):.4f}-{np.percentile(ratio, 99):.4f}")
    assert cal.unit == UNIT_ABSOLUTE and cal.responsivity.shape == (SIZE, 204)
    assert abs(np.median(ratio) - 1) < 0.003 and np.percentile(np.abs(ratio - 1), 99) < 0.02
    # the certificate's 1 % and the measured spread
    assert 0.0099 < np.median(cal.uncertainty) < 0.02
    assert {s["role"] for s in cal.sources} >= {"capture", "source"}
    assert all(s["sha256"] for s in cal.sources)


def test_fuse_with_calibration_gives_absolute_radiance(captures, tmp_path):
    from mehs.calibration.accuracy import radiance_accuracy
    from mehs.io.envi import read_envi

    cal = tmp_path / "cal.json"
    assert main(["calibrate", str(captures["sphere"]), "--source",
                 str(captures["sphere"] / "truth/source_radiance.csv"), "--out", str(cal)]) == 0
    assert main(["fuse", str(captures["window"]), "--out", str(tmp_path / "f"),
                 "--calibration", str(cal)]) == 0
    rad = read_envi(tmp_path / "f" / "radiance.hdr")
    assert rad.units == UNIT_ABSOLUTE
    truth = read_envi(captures["window"] / "truth" / "radiance.hdr")
    import cv2

    mask = cv2.imread(str(tmp_path / "f" / "mask.png"), cv2.IMREAD_UNCHANGED)
    vis = (rad.wavelengths >= 420) & (rad.wavelengths <= 700)
    acc = radiance_accuracy(np.asarray(rad.data)[..., vis], np.asarray(truth.data)[..., vis], mask)
    print(f"window scene, 204 bands (420-700 nm) vs truth: {acc}")
    assert abs(acc["scale"] - 1) < 0.02          # absolute level, no fitted scale
    summary = json.loads((tmp_path / "f" / "summary.json").read_text())
    assert summary["units"] == UNIT_ABSOLUTE and summary["calibration"]["method"] == "source-absolute"


def test_panel_calibration_is_relative_and_shapes_are_right(captures):
    from mehs.synthesis.bracket import load_bracket

    br = load_bracket(captures["window"])        # white tile: 99 % panel under illuminant A
    panel = Spectrum(np.array([300.0, 1100.0]), np.array([0.99, 0.99]), "flat 0.99")
    ill = Spectrum(np.arange(300.0, 1101.0, 1.0), np.array([0.0]) + 1.0, "x")  # placeholder
    from mehs.capture.scene import illuminant_spectrum

    wl = np.arange(300.0, 1101.0, 1.0)
    ill = Spectrum(wl, illuminant_spectrum("A", wl), "A extended")
    cal = calibrate_panel_relative(br, panel, ill, region="white")
    truth = np.asarray(json.loads((captures["window"] / "scene.json").read_text())
                       ["truth_dn_per_ms_per_radiance"])
    q = cal.responsivity.mean(axis=0) / truth
    q /= np.median(q)
    assert cal.unit == UNIT_RELATIVE
    assert np.percentile(np.abs(q - 1), 95) < 0.03     # spectral shape of the responsivity


def test_bad_calibration_input_is_refused_and_nothing_written(captures, tmp_path, capsys):
    from mehs.synthesis.bracket import load_bracket

    sph = captures["sphere"]
    out = tmp_path / "c.json"
    # a certificate that does not cover the camera's bands
    short = tmp_path / "short.csv"
    short.write_text("wavelength,radiance\n400,1\n500,1\n600,1\n700,1\n")
    assert main(["calibrate", str(sph), "--source", str(short), "--out", str(out)]) == 2
    assert "covers 400..700 nm" in capsys.readouterr().err and not out.exists()
    # a panel file of garbage
    bad = tmp_path / "bad.csv"
    bad.write_text("nm,value\n400,0.9\n500,oops\n")
    assert main(["calibrate", str(sph), "--panel", str(bad), "--illuminant", "D65",
                 "--out", str(out)]) == 2
    assert "not numbers" in capsys.readouterr().err and not out.exists()
    # negative / NaN responsivity in a file
    cal = calibrate_source_absolute(load_bracket(sph), load_spectrum(sph / "truth/source_radiance.csv"))
    p = cal.save(tmp_path / "ok.json")
    d = json.loads(p.read_text())
    d["responsivity"][5] = -1.0
    (tmp_path / "neg.json").write_text(json.dumps(d))
    with pytest.raises(MehsError, match="negative"):
        Calibration.load(tmp_path / "neg.json")
    d["responsivity"][5] = float("nan")
    (tmp_path / "nan.json").write_text(json.dumps(d).replace("NaN", "NaN"))
    with pytest.raises(MehsError, match="NaN"):
        Calibration.load(tmp_path / "nan.json")
    # another band set / another camera / another width
    with pytest.raises(MehsError, match="other wavelengths"):
        cal.check_compatible(cal.wavelengths + 1.0, SIZE)
    with pytest.raises(MehsError, match="204 bands, the data 31"):
        cal.check_compatible(np.arange(400.0, 701.0, 10.0), SIZE)
    with pytest.raises(MehsError, match="camera"):
        cal.check_compatible(cal.wavelengths, SIZE, camera_id="SPECIM,IQ,000123")
    with pytest.raises(MehsError, match="spatial columns"):
        cal.check_compatible(cal.wavelengths, 2 * SIZE)
    # fuse refuses it before writing anything
    assert main(["fuse", str(captures["window"]), "--out", str(tmp_path / "nf"),
                 "--calibration", str(tmp_path / "neg.json")]) == 2
    assert not (tmp_path / "nf" / "radiance.hdr").exists()


def test_certificate_round_trip(tmp_path):
    p = sphere_certificate(tmp_path / "c.csv")
    s = load_spectrum(p)
    assert s.wavelengths[0] == 350 and s.wavelengths[-1] == 1100
    assert s.uncertainty is not None and np.allclose(s.uncertainty, 0.01)


def test_panel_under_a_colour_science_illuminant_calibrates_the_covered_bands(captures, tmp_path,
                                                                               capsys):
    # colour-science's CIE A ends at 780 nm; a 1000 nm camera is refused unless --partial,
    # then calibrated over what the illuminant covers, and its cubes hold those bands
    from mehs.io.envi import read_envi

    cap = captures["window"]                          # white tile: 99 % panel under A
    out = tmp_path / "p.json"
    assert main(["calibrate", str(cap), "--panel", "0.99", "--illuminant", "A",
                 "--out", str(out)]) == 2
    assert "--partial" in capsys.readouterr().err and not out.exists()
    assert main(["calibrate", str(cap), "--panel", "0.99", "--illuminant", "A", "--partial",
                 "--out", str(out)]) == 0
    assert "calibrated 1" in capsys.readouterr().out
    cal = Calibration.load(out)
    assert not cal.complete and cal.calibrated_wavelengths[-1] < 780
    assert cal.calibrated_wavelengths[0] < 400
    assert main(["fuse", str(cap), "--out", str(tmp_path / "f"), "--calibration", str(out)]) == 0
    rad = read_envi(tmp_path / "f" / "radiance.hdr")
    assert rad.units == UNIT_RELATIVE and rad.bands == cal.bands.size
    assert np.allclose(rad.wavelengths, cal.calibrated_wavelengths)
    # the shape of the calibrated spectra against the truth (one scale: relative radiance)
    truth = read_envi(cap / "truth" / "radiance.hdr")
    t = np.asarray(truth.data, dtype=np.float64)[..., cal.bands]
    r = np.asarray(rad.data, dtype=np.float64)
    vis = (cal.calibrated_wavelengths >= 420) & (cal.calibrated_wavelengths <= 700)
    from mehs.calibration.accuracy import radiance_accuracy
    import cv2

    mask = cv2.imread(str(tmp_path / "f" / "mask.png"), cv2.IMREAD_UNCHANGED)
    acc = radiance_accuracy(r[..., vis], t[..., vis], mask, absolute=False)
    print(f"relative calibration from the white tile: {acc}")
    assert acc["rel_error_median"] < 0.05


def test_calibration_refuses_data_linearised_by_another_curve_or_bit_depth(captures, tmp_path,
                                                                           capsys):
    from mehs.synthesis.bracket import load_bracket
    from mehs.synthesis.response import ResponseCurve

    sph = captures["sphere"]
    cal = calibrate_source_absolute(load_bracket(sph), load_spectrum(sph / "truth/source_radiance.csv"))
    assert cal.response["method"] == "linear" and cal.response["g_sha256"]
    p = cal.save(tmp_path / "cal.json")
    # made under the linear curve: the responsivity is wrong for data linearised by a
    # recovered curve (26-38 % on a gamma sensor), so fuse refuses before writing
    assert main(["fuse", str(captures["window"]), "--out", str(tmp_path / "f"),
                 "--response", "debevec", "--calibration", str(p)]) == 2
    err = capsys.readouterr().err
    assert "linear response" in err and "--response linear" in err
    assert not (tmp_path / "f" / "radiance.hdr").exists()
    lin = ResponseCurve.linear(12)
    cal.check_compatible(cal.wavelengths, SIZE, bit_depth=12, response=lin)   # the same: fine
    with pytest.raises(MehsError, match="12-bit data, the data are 16-bit"):
        cal.check_compatible(cal.wavelengths, SIZE, bit_depth=16, response=ResponseCurve.linear(16))
    # two different recovered curves: a warning naming the calibration's curve
    bent = ResponseCurve(np.log(np.maximum(np.arange(4096.0), 0.5) ** 1.1), 12, method="debevec1997")
    other = ResponseCurve(np.log(np.maximum(np.arange(4096.0), 0.5) ** 1.2), 12, method="debevec1997")
    cal.response = {"method": "debevec1997", "path": "ladder/response.json",
                    "g_sha256": bent.fingerprint()}
    cal.check_compatible(cal.wavelengths, SIZE, response=ResponseCurve.load(bent.save(tmp_path / "r.json")))
    with pytest.warns(UserWarning, match="ladder/response.json"):
        cal.check_compatible(cal.wavelengths, SIZE, response=other)
