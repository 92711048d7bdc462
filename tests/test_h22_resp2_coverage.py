"""A curve above the levels the bracket's pairs of exposures tie: continued as a power law,
and a bracket read there flagged.

On the simulator's ``window`` scene (a dark chart under tungsten light, a daylight window
~10⁴× brighter in view) with a gamma-0.8 sensor and 2 exposures 0.5 / 2 ms, the long
exposure sees the chart only (pairs reach level ~470 of 4095) while the short one alone
reads the window at 1540–4013. The prior continued ``g`` as a straight line in ``z`` there:
the curve ran 20× off the true one at the top, the window read ~17× too bright relative to
the chart, and the self-check passed it (median 0.9 %). Truth: the sensor model's own
inverse response (``SensorModel.inverse_response_dn``) and the simulator's radiance.
"""

import warnings

import numpy as np
import pytest

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from mehs.cube import SpectralCube
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.fuse import fuse_bracket
from mehs.synthesis.response_extend import extend_power_law


def _window(times, gamma=0.8, n=40):
    wl = SPECIM_IQ_WAVELENGTHS[::8].copy()
    scene = make_scene("window", lines=n, samples=n, seed=1, wavelengths=wl,
                       fwhm=np.full(wl.size, 7.0))
    sensor = SensorModel(seed=1, response="gamma", gamma=gamma)
    sim = simulate_bracket(scene, sensor, list(times), seed=1, white=False)
    br = Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks),
                 [None] * len(times), sim.times_ms, wl, bit_depth=12)
    return br, sim, sensor


def _fuse(br, check=True):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fuse_bracket(br, ghosts="off", check_response=check)


def _paired_top(sim):
    """The highest raw level seen unsaturated, above the dark, by a (pixel, band) that has
    another such exposure: what a pair of exposures can tie."""
    X = np.stack([np.asarray(e) for e in sim.exposures]).astype(np.float64)
    ok = (X < 0.98 * 4095) & (X > float(np.median(np.asarray(sim.darks))) + 2)
    paired = ok & (ok.sum(axis=0) >= 2)[None]
    return int(X[paired].max())


def _beyond_vs_rest(res, sim):
    """Median radiance/truth of the samples read only far above the pairs (the window)
    over that of the rest (the chart): 1 for a right curve."""
    X = np.stack([np.asarray(e) for e in sim.exposures]).astype(np.float64)
    usable = X < 0.98 * 4095
    truth = np.asarray(sim.truth, np.float64) * sim.truth_dn_per_ms
    ok = usable.any(axis=0) & (truth > 1)
    hi = _paired_top(sim)
    top = np.where(usable, X, 0).max(axis=0)
    ratio = np.asarray(res.radiance.data, np.float64) / truth
    beyond = ok & (top > 1.25 * hi)
    return float(np.median(ratio[beyond]) / np.median(ratio[ok & ~beyond])), int(beyond.sum())


def test_power_law_continuation_is_exact_for_gamma_and_linear():
    z = np.arange(4096, dtype=np.float64)
    for p in (1.0, 1.25, 2.0):
        true = np.log(np.maximum(z, 0.5) ** p)
        cut = true.copy()
        cut[600:] = cut[599] + (z[600:] - 599) * (cut[599] - cut[598])   # the prior's line
        got = extend_power_law(cut, 599)
        assert np.allclose(got, true, atol=1e-9)


def test_window_read_by_one_exposure_follows_the_true_curve():
    br, sim, sensor = _window([0.5, 2.0])
    res = _fuse(br, check=False)
    assert res.response.method == "debevec1997"
    hi = _paired_top(sim)
    assert hi < 1000                        # the pairs stop far below the window's levels
    # the curve's linear secant above the dark level, one scale out, against the sensor's
    d0 = float(np.median(np.asarray(sim.darks)))
    z = np.arange(4096, dtype=np.float64)
    f = np.exp(res.response.table()[0])
    ft = sensor.inverse_response_dn(z)
    lv = np.arange(int(d0) + 50, 4013)
    r = (f[lv] - np.interp(d0, z, f)) / (ft[lv] - sensor.inverse_response_dn(d0))
    r = r / np.median(r[lv <= hi])
    assert np.max(np.abs(r[lv > 3000] - 1)) < 0.3        # before: 20×
    ratio, n = _beyond_vs_rest(res, sim)
    assert n > 100 and 0.7 < ratio < 1.45                  # before: 17×


def test_check_flags_a_window_read_beyond_the_pairs():
    br, sim, _ = _window([0.5, 2.0])
    res = _fuse(br)
    chk = res.summary["response"]["check"]
    assert res.summary["response_undetermined"]
    assert chk["read_beyond_coverage"] > chk["read_beyond_tolerance"]
    assert "no pair of exposures" in chk["reason"] and "shorter" in chk["reason"]
    assert any("no pair of exposures" in w for w in res.summary["warnings"])


@pytest.mark.parametrize("times", [[0.05, 0.2, 0.8], [0.5, 2.0, 8.0, 32.0, 128.0]])
def test_brackets_whose_pairs_reach_saturation_read_nothing_beyond(times):
    # a short first exposure (the window paired by the next) or a 5-exposure ladder
    br, sim, _ = _window(times)
    res = _fuse(br)
    chk = res.summary["response"].get("check", {})
    assert res.response.parameters["covered_top_level"] > 3500
    assert chk.get("read_beyond_coverage", 0.0) == 0.0
    assert "no pair of exposures" not in str(chk.get("reason"))
