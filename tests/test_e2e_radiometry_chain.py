"""The whole radiometric chain against outside truth: simulator radiance → dataset files.

A small lamp scene (a light source that saturates, dark patches) is simulated, written as
a scene folder and built into a dataset with the sensor's known linear curve and with a
radiometric calibration from the simulated integrating sphere. Every stored file is then
held against references computed *from the simulator's truth* with other libraries:

- ``hs.hdr`` against SPy's ``BandResampler`` of the true radiance (same band model);
- ``hdr_rgb.exr`` against colour-science's ``msds_to_XYZ`` (CIE 1931 2°, the 31 bands,
  equal-energy weighting) → sRGB, of the same resampled truth;
- ``ldr_rgb.png`` against the documented exposure rule applied to the stored half floats;
- the saturation flags against the pixels the noise-free sensor model saturates.

Audit figures (32×32, 204 bands, six scene kinds, 2–5 exposures): median signed bias of
every stage within ±0.3 %, so the tolerances below are loose on purpose — they catch a
lost scale (π, 2^k, a band's width), a swapped channel or a wrong flag, not noise.
"""

from __future__ import annotations

import numpy as np
import pytest

colour = pytest.importorskip("colour")
spectral = pytest.importorskip("spectral")
cv2 = pytest.importorskip("cv2")

WL_STEP = 3            # every 3rd Specim IQ band: 68 bands, 3 s for the whole module
TIMES_MS = (0.02, 0.64, 20.48)
WL31 = np.arange(400.0, 701.0, 10.0)


def _spy_31(cube, wl, fwhm):
    r = spectral.BandResampler(list(wl), list(WL31), list(fwhm), [10.0] * 31)
    flat = np.asarray(cube, dtype=np.float64).reshape(-1, len(wl))
    return np.stack([r(s) for s in flat]).reshape(cube.shape[:2] + (31,))


def _colour_srgb(spec31):
    shape = colour.SpectralShape(400, 700, 10)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    xyz = colour.msds_to_XYZ(spec31.reshape(-1, 31), cmfs, colour.sd_ones(shape),
                             method="Integration", shape=shape) / 100.0
    rgb = colour.XYZ_to_RGB(xyz, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_encoding=False)
    return np.maximum(rgb, 0).reshape(spec31.shape[:2] + (3,))


def _read_exr(path):
    import OpenEXR

    ch = OpenEXR.File(str(path)).channels()
    if "RGB" in ch:
        return np.asarray(ch["RGB"].pixels, dtype=np.float64)
    return np.stack([np.asarray(ch[c].pixels, dtype=np.float64) for c in "RGB"], axis=-1)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    from mehs.calibration import calibrate_source_absolute, load_spectrum
    from mehs.calibration.targets import sphere_certificate
    from mehs.capture.scene import SPECIM_IQ_FWHM, SPECIM_IQ_WAVELENGTHS, make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket, write_simulated_scene
    from mehs.dataset.build import build_dataset
    from mehs.synthesis.bracket import load_bracket
    from mehs.synthesis.response import ResponseCurve

    root = tmp_path_factory.mktemp("e2e")
    wl, fw = SPECIM_IQ_WAVELENGTHS[::WL_STEP], SPECIM_IQ_FWHM[::WL_STEP]
    sensor = SensorModel(seed=3, wavelengths=wl)
    scene = make_scene("lamp", 24, 24, wavelengths=wl, fwhm=fw, seed=1)
    sim = simulate_bracket(scene, sensor, TIMES_MS)
    cap = write_simulated_scene(sim, root / "lamp")
    sphere = simulate_bracket(make_scene("sphere", 8, 24, wavelengths=wl, fwhm=fw), sensor,
                              (5.0, 20.0, 40.0))
    cal = calibrate_source_absolute(load_bracket(write_simulated_scene(sphere, root / "sphere")),
                                    load_spectrum(sphere_certificate(root / "cert.csv")))
    cal_path = cal.save(root / "cal.json") or root / "cal.json"
    curve = ResponseCurve.linear(12).save(root / "linear.json")
    out = {}
    for name, c in (("dn", None), ("cal", cal_path)):
        ds = root / f"ds_{name}"
        m = build_dataset([cap], ds, workers=1, progress=False, response=curve, calibration=c)
        out[name] = (ds, m["scenes"][0])
    return sim, sensor, out


@pytest.mark.parametrize("which", ["dn", "cal"])
def test_stored_files_match_references_from_the_truth(built, which):
    from mehs.io.envi import read_envi

    sim, _, out = built
    ds, entry = out[which]
    q, files = entry["quality"], entry["files"]
    scale = float(q["radiance_scale"])
    truth = np.asarray(sim.truth, dtype=np.float64)
    if which == "dn":
        truth = truth * sim.truth_dn_per_ms          # uncalibrated: linear DN per ms
    mask = cv2.imread(str(ds / files["mask"]), cv2.IMREAD_UNCHANGED)
    ok = mask == 0
    assert 0 < (~ok).sum() < ok.sum()               # the lamp is flagged, the rest is not

    t31 = _spy_31(truth, sim.wavelengths, sim.fwhm)
    hs = np.asarray(read_envi(ds / files["hs"]).data, dtype=np.float64) / scale
    rel = (hs[ok] - t31[ok]) / t31[ok]
    assert abs(np.median(rel)) < 0.01, np.median(rel)
    assert np.median(np.abs(rel)) < 0.06, np.median(np.abs(rel))

    exr = _read_exr(ds / files["hdr_rgb"])
    ref = _colour_srgb(t31)
    lum = np.array([0.2126, 0.7152, 0.0722])
    ry = (exr[ok] @ lum) / scale / (ref[ok] @ lum) - 1
    assert abs(np.median(ry)) < 0.01, np.median(ry)
    assert np.percentile(np.abs(ry), 95) < 0.05

    # the LDR image follows the documented rule from the stored half floats
    ldr = cv2.imread(str(ds / files["ldr_rgb"]), cv2.IMREAD_UNCHANGED)[..., ::-1]
    enc = colour.cctf_encoding(np.clip(exr * q["ldr_exposure"], 0, 1), function="sRGB")
    assert np.array_equal(ldr, np.rint(enc * 255).astype(np.uint8))
    # ... and its exposure is the log-average rule on the truth, up to the noise
    y = ref @ lum
    expo = 0.18 / np.exp(np.mean(np.log(y[y > 0]))) / scale
    assert q["ldr_exposure"] == pytest.approx(expo, rel=0.02)


def test_saturation_flags_are_the_pixels_the_sensor_saturates(built):
    sim, sensor, out = built
    ds, entry = out["dn"]
    mask = cv2.imread(str(ds / entry["files"]["mask"]), cv2.IMREAD_UNCHANGED)
    dn0 = sensor.expected_dn(sim.truth, TIMES_MS[0], wavelengths=sim.wavelengths)
    surely = (dn0 >= sensor.saturation_dn).any(axis=2)       # saturated without noise
    never = (dn0 < 0.9 * sensor.saturation_dn).all(axis=2)   # far from it in every band
    flagged = (mask & 1) > 0
    assert surely.any()
    assert flagged[surely].all()
    assert not flagged[never].any()
    assert entry["quality"]["saturated_fraction"] == pytest.approx(flagged.mean())
