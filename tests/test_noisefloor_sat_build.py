"""A built dataset's noise model where the long exposure saturates, against the simulator.

A ColorChecker bracket of 0.02 and 10 ms (×500): the brighter patches saturate the long
exposure, and their ground truth is the short exposure's alone. Before: the model pooled
both exposures there, ``|hs − truth|/σ`` had std 32 in those elements and no pixel got
mask bit 8, although 46 of 576 had a spectrum SNR below 7 against the truth.
"""

import json

import cv2
import numpy as np
import pytest

from mehs.capture.scene import make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket, write_simulated_scene

TIMES = (0.02, 10.0)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    from mehs.cube import SpectralCube
    from mehs.dataset.build import build_dataset
    from mehs.io.envi import read_envi
    from mehs.rgb import WAVELENGTHS_31
    from mehs.synthesis.resample import resample_cube, resampling_matrix
    from mehs.synthesis.response import ResponseCurve

    root = tmp_path_factory.mktemp("noisefloor_sat")
    sensor = SensorModel(seed=3)
    sc = make_scene("colorchecker", 24, 24, seed=1, source_ratio=0)
    dn = simulate_bracket(sc, sensor, TIMES, white=False)
    # the 99th percentile of the radiance at 8000 DN/ms: 2× saturation in the long exposure
    k = np.float32(8000.0 / np.percentile(np.asarray(dn.truth) * dn.truth_dn_per_ms, 99))
    sc.radiance = sc.radiance * k
    sc.white_radiance = sc.white_radiance * k
    sim = simulate_bracket(sc, sensor, TIMES)
    folder = write_simulated_scene(sim, root / "cc", overwrite=True)
    ResponseCurve.linear(12).save(root / "lin.json")
    m = build_dataset([folder], root / "ds", workers=1, progress=False,
                      response=root / "lin.json", ghosts="off")
    entry = m["scenes"][0]
    truth = np.asarray(sim.truth, np.float32) * sim.truth_dn_per_ms.astype(np.float32)
    s = np.float32(entry["quality"]["radiance_scale"])
    t31 = resample_cube(SpectralCube(truth, sim.wavelengths, fwhm=sim.fwhm),
                        WAVELENGTHS_31).data * s
    gt = read_envi(root / "ds" / entry["files"]["hs"]).data
    mask = cv2.imread(str(root / "ds" / entry["files"]["mask"]), cv2.IMREAD_UNCHANGED)
    # the share of each band's variance from native bands that saturate the long exposure
    M = resampling_matrix(sim.wavelengths, WAVELENGTHS_31, method="gaussian",
                          src_fwhm=sim.fwhm, dst_fwhm=10.0)
    ys = 0.98 * 4095 - sensor.black_level_dn
    w = (truth * TIMES[1] >= ys).astype(np.float64) @ (M * M).T / (M * M).sum(1)
    # the brightest native band of each band's window, over saturation in the long exposure
    r = np.stack([(truth * (M[b] > 1e-3 * M[b].max())).max(-1) for b in range(31)], -1)
    w[r * TIMES[1] >= 0.9 * ys] = np.maximum(w[r * TIMES[1] >= 0.9 * ys], 1e-3)
    return (root / "ds", entry, np.asarray(t31, np.float64), np.asarray(gt, np.float64),
            mask, w)


def test_fusion_json_records_where_each_exposure_saturates(built):
    ds, entry, *_ = built
    fus = json.loads((ds / entry["files"]["hs"]).parent.joinpath("fusion.json").read_text())
    lev = np.asarray(fus["saturation_linear_dn"])
    assert lev.shape == (2, 204)
    # the ADC's 0.98·4095 less the black level (32 DN) and the dark current's mean
    assert np.all((lev > 3900) & (lev < 4000))
    assert "exposures" in entry["quality"]["noise_model"]


def test_sigma_matches_the_truth_where_the_long_exposure_saturated(built):
    from mehs.dataset.noisefloor import sigma

    _, entry, t31, gt, mask, w = built
    s = sigma(t31, entry["quality"]["noise_model"])
    z = (gt - t31) / s
    ok = (mask & 1 == 0)[..., None]
    short = ok & (w > 1 - 1e-3)              # the short exposure alone
    both = ok & (w < 1e-3)                   # both, clear of the step (< 90 % of saturation)
    assert short.sum() > 3000 and both.sum() > 1000
    assert 0.85 < z[short].std() < 1.2, z[short].std()        # was 32
    assert 0.85 < z[both].std() < 1.2, z[both].std()


def test_pixels_the_short_exposure_does_not_resolve_are_flagged(built):
    _, entry, t31, gt, mask, w = built
    snr = np.sqrt((t31 ** 2).sum(-1) / ((gt - t31) ** 2).sum(-1))   # against the truth
    low = (snr < 7) & (mask & 1 == 0)
    high = (snr > 20) & (mask & 1 == 0)
    assert low.sum() >= 20
    assert np.mean(mask[low] & 8 > 0) > 0.5, np.mean(mask[low] & 8 > 0)      # was 0
    assert np.mean(mask[high] & 8 > 0) < 0.05
    assert entry["quality"]["noise_floor_fraction"] == pytest.approx(np.mean(mask & 8 > 0))
