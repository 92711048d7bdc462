"""The linearity test of ``response="auto"`` on a small probe, refined when unclear (issue 16).

The first probe reads :data:`mehs.synthesis.noise.PROBE_PIXELS` pixels; a result that is
not clear-cut is decided again on :data:`~mehs.synthesis.noise.PROBE_PIXELS_FINE`. The
per-group medians that set the statistics' clip come from one sort instead of a loop of
``np.median`` calls; they must equal ``np.median`` of each group.
"""

from __future__ import annotations

import numpy as np
import pytest

from mehs.cube import SpectralCube
from mehs.synthesis import _ptc_groups as G
from mehs.synthesis import noise as N
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.fuse_response import LINEARITY_TOLERANCE, linearity_auto


def _bracket(response: str, size: int = 96, times=(0.05, 0.4, 3.2)) -> Bracket:
    from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket

    wl = SPECIM_IQ_WAVELENGTHS[::4]
    sc = make_scene("window", lines=size, samples=size, wavelengths=wl, seed=1)
    sim = simulate_bracket(sc, SensorModel(response=response, seed=2), list(times), seed=3)
    return Bracket([SpectralCube(e, sc.wavelengths) for e in sim.exposures], list(sim.darks),
                   [None] * len(times), sim.times_ms, sc.wavelengths, bit_depth=12)


def _sat(br: Bracket) -> np.ndarray:
    return np.full(br.shape[2], 0.98 * 4095, np.float32)


def _count_probes(monkeypatch) -> list:
    """The ``max_pixels`` of every ``noise.probe_bracket`` call from now on."""
    calls = []
    real = N.probe_bracket

    def counting(*a, **k):
        calls.append(k.get("max_pixels"))
        return real(*a, **k)

    monkeypatch.setattr(N, "probe_bracket", counting)
    return calls


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_group_medians_equal_numpys(seed):
    rng = np.random.default_rng(seed)
    groups = 40
    n = 5000
    g = rng.integers(0, groups - 3, n)                  # the last groups stay empty
    v = rng.normal(0, 1, n) * rng.choice([1e-3, 1.0, 1e4], n)
    v[:7] = 0.0
    v[7:9] = -0.0
    med, sig = G._group_median_mad(v, g, groups)
    for gi in range(groups):
        dv = v[g == gi]
        if dv.size == 0:
            assert med[gi] == 0 and sig[gi] == 0
            continue
        m = np.median(dv.astype(np.float32).astype(np.float64))
        mad = np.median(np.abs(dv - m).astype(np.float32).astype(np.float64))
        assert med[gi] == m
        assert sig[gi] == 1.4826 * mad
        # float32-rounded values: within float32 precision of numpy's float64 median
        assert med[gi] == pytest.approx(np.median(dv), rel=1e-6, abs=1e-30)


def test_order_keys_sort_like_the_float32_values():
    # every class of float32: ±0, subnormals, the extremes, ±inf; keys below 2**32
    tiny = np.finfo(np.float32).smallest_subnormal
    big = np.finfo(np.float32).max
    v = np.concatenate((np.array([0.0, -0.0, tiny, -tiny, 2 * tiny, big, -big, np.inf,
                                  -np.inf, 1.0, -1.0], np.float32),
                        (np.random.default_rng(4).normal(0, 1, 4000)
                         * 10.0 ** np.linspace(-44, 38, 4000)).astype(np.float32)))
    k = G._order_keys(v)
    assert k.dtype == np.uint64 and k.max() < 2 ** 32
    order = np.argsort(k, kind="stable")
    assert np.all(v[order][1:] >= v[order][:-1])             # sorted like the values
    assert np.unique(k).size == np.unique(v.view(np.uint32)).size     # one key a value
    assert G._order_keys(np.array([-0.0], np.float32))[0] < G._order_keys(
        np.array([0.0], np.float32))[0]
    # the keys themselves, for any input the medians pass (float64 rounded to float32 —
    # subnormal, zero or inf there —, NaNs, other byte orders, strides): the flip of
    # the float32 bits written out as a reference
    x = np.concatenate((v.astype(np.float64), [np.nan, -np.nan, 1e-320, -1e-320, 1e39,
                                               -1e39, 3.4e38]))
    x = np.concatenate((x, np.random.default_rng(5).normal(0, 1, 3000)
                        * 10.0 ** np.linspace(-320, 300, 3000)))
    with np.errstate(over="ignore"):            # values beyond float32 round to ±inf
        for inp in (x, x.astype(">f8"), x.astype(np.float32).astype(">f4"), x[::-3]):
            b = np.asarray(inp, np.float32).astype(np.float32).view(np.uint32).astype(np.uint64)
            ref = np.where(b >= 2 ** 31, b ^ np.uint64(0xFFFFFFFF), b | np.uint64(2 ** 31))
            np.testing.assert_array_equal(G._order_keys(inp), ref)


def test_even_and_odd_group_sizes():
    v = np.array([3.0, 1.0, 2.0, 10.0, 4.0, 1.0, 2.0])
    g = np.array([0, 0, 0, 1, 1, 1, 1])
    med, _ = G._group_median_mad(v, g, 2)
    assert med.tolist() == [2.0, 3.0]


def test_a_linear_sensor_is_settled_on_the_small_probe():
    br = _bracket("linear")
    assert br.shape[0] * br.shape[1] > N.PROBE_PIXELS
    probe, lin = linearity_auto(br, _sat(br))
    assert lin["probe_pixels"] <= N.PROBE_PIXELS and "probe_refined" not in lin
    assert lin["deviation"] < LINEARITY_TOLERANCE / 2
    assert lin["resolution"] < LINEARITY_TOLERANCE / 2
    # the same verdict as the finer probe would give
    fine = N.linearity_PTC(N.probe_bracket(br, _sat(br), max_pixels=N.PROBE_PIXELS_FINE),
                           lambda raw, dark, j: raw - dark)
    assert fine["deviation"] < LINEARITY_TOLERANCE and fine["resolution"] < LINEARITY_TOLERANCE
    assert probe.raw.shape[1] == lin["probe_pixels"]


def test_a_non_linear_sensor_is_decided_on_the_finer_probe():
    br = _bracket("gamma")
    probe, lin = linearity_auto(br, _sat(br))
    assert lin.get("probe_refined") is True
    assert N.PROBE_PIXELS < lin["probe_pixels"] <= N.PROBE_PIXELS_FINE
    assert probe.raw.shape[1] == lin["probe_pixels"]
    assert lin["deviation"] > LINEARITY_TOLERANCE


def test_fuse_probes_once_and_reports_the_probe(monkeypatch):
    from mehs.synthesis.fuse import fuse_bracket

    calls = _count_probes(monkeypatch)
    res = fuse_bracket(_bracket("linear"), ghosts="off")
    resp = res.summary["response"]
    assert res.response.is_linear and resp["linearity_conclusive"] is True
    assert resp["linearity_probe_pixels"] <= N.PROBE_PIXELS
    # the noise model reuses the linearity test's probe and statistics
    assert calls == [N.PROBE_PIXELS]
    assert res.summary["noise"]["source"] == "photon transfer (bracket)"


def test_a_first_probe_of_every_pixel_is_not_read_again(monkeypatch):
    """Few bands: the first probe already reads every pixel (noise.probe_pixels), so a
    result that is not clear-cut has nothing more to gain from a second one."""
    from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket

    wl = SPECIM_IQ_WAVELENGTHS[[40, 100, 160]]
    sc = make_scene("window", lines=96, samples=96, wavelengths=wl, seed=1)
    sim = simulate_bracket(sc, SensorModel(response="gamma", seed=2), [0.05, 0.4, 3.2], seed=3)
    br = Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks), [None] * 3,
                 sim.times_ms, wl, bit_depth=12)
    assert 96 * 96 > N.PROBE_PIXELS and N.probe_pixels(N.PROBE_PIXELS, 3) >= 96 * 96
    calls = _count_probes(monkeypatch)
    probe, lin = linearity_auto(br, _sat(br))
    assert calls == [N.PROBE_PIXELS] and "probe_refined" not in lin
    assert lin["probe_pixels"] == 96 * 96 == probe.raw.shape[1]
