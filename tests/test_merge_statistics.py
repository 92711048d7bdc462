"""The merge's statistics against independent truth: textbook estimators, the
simulated sensor's parameters, and the conventions the merge itself documents."""

from __future__ import annotations

import numpy as np
import pytest

from mehs.synthesis.ghost import deghost_from_reference
from mehs.synthesis.merge import MASK_SATURATED, merge_bracket


def test_deghost_keeps_the_shortest_lower_bound_of_a_band_saturated_everywhere():
    """A lamp band saturated in every exposure is y₀/t₀ in the merge (mask bit 1). The
    de-ghosting's fall-back ended on the reference's own saturated value over its longer
    time: with the 8 ms exposure as reference, 508 DN/ms instead of 4063 (t_ref/t₀ = 8×)."""
    t = np.array([1.0, 8.0, 64.0])
    stack = []
    for tj in t:
        a = np.empty((4, 4, 2), np.uint16)
        a[..., 0] = 4095                          # the lamp: clipped in every exposure
        a[..., 1] = np.uint16(32 + 1.0 * tj)      # dark: below the floor at 1 ms
        stack.append(a)
    darks = [np.full((4, 2), 32.0, np.float32)] * 3
    sat = np.full(2, 0.98 * 4095)
    m = merge_bracket(stack, t, darks=darks, saturation=sat)
    assert m.mask[0, 0] & MASK_SATURATED
    assert m.radiance[0, 0, 0] == pytest.approx(4063.0)
    rad = np.array(m.radiance)
    ghost = np.zeros((4, 4), bool)
    ghost[1:3, 1:3] = True
    ref = deghost_from_reference(rad, ghost, stack, darks, t,
                                 linearise=lambda raw, dk, j: raw - dk, saturation=sat,
                                 floor=2.0, calibration=np.ones(2))
    assert ref == 1                               # most samples above the floor
    np.testing.assert_allclose(rad[1:3, 1:3, 0], 4063.0)
    np.testing.assert_allclose(rad[1:3, 1:3, 1], 1.0)


def test_a_short_scan_of_a_wide_sensor_still_measures_its_noise():
    """4 lines × 9000 pixels: the probe's step through the pixels is 9 lines, and its first
    line (step // 2 = 4) lay past the scan's end — nothing probed, and the noise model fell
    back to the recorded sensor or the default (gain 1 DN/e⁻ instead of 0.25)."""
    from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
    from mehs.capture.sensor import SensorModel
    from mehs.capture.simulate import simulate_bracket
    from mehs.cube import SpectralCube
    from mehs.synthesis.bracket import Bracket
    from mehs.synthesis.fuse import estimate_noise
    from mehs.synthesis.noise import probe_bracket
    from mehs.synthesis.response import ResponseCurve

    wl = SPECIM_IQ_WAVELENGTHS[100:104]
    sc = make_scene("ramp", lines=4, samples=9000, seed=1, wavelengths=wl)
    sen = SensorModel(seed=1)
    sim = simulate_bracket(sc, sen, (1.0, 4.0, 16.0), seed=1, white=False)
    br = Bracket([SpectralCube(e, wl) for e in sim.exposures], sim.darks, [None] * 3,
                 sim.times_ms, wl, bit_depth=12)
    sat = np.full(wl.size, 0.98 * 4095, np.float32)
    # every line: 4 bands read 12× the pixels of 48 or more (noise.probe_pixels), and
    # the scan holds fewer (a probe of one line of many bands: test_noise_probe_size.py)
    assert probe_bracket(br, sat).raw.shape[1] == 4 * 9000
    model, diag = estimate_noise(br, ResponseCurve.linear(12), sat)
    assert "fallback" not in diag, diag
    assert model.gain == pytest.approx(sen.gain_dn_per_e, rel=0.05)


def test_a_saturation_level_beyond_the_largest_code_is_refused():
    import pytest

    from mehs.errors import InputError
    from mehs.synthesis.merge import merge_bracket

    z = [np.full((2, 3, 4), 100, np.uint16), np.full((2, 3, 4), 4095, np.uint16)]
    # above 4095 a clipped sample would count as a measurement
    with pytest.raises(InputError, match=r"saturation must be in \(0, 4095\]"):
        merge_bracket(z, [1.0, 4.0], bit_depth=12, saturation=5000)
    with pytest.raises(InputError, match="saturation"):
        merge_bracket(z, [1.0, 4.0], bit_depth=12, saturation=np.array([4000, 4000, np.nan, 4000]))


@pytest.mark.parametrize("method", ["poisson", "debevec"])
def test_per_band_levels_given_as_strided_views_merge_as_contiguous_ones(method, tmp_path,
                                                                         monkeypatch):
    """A per-band saturation or calibration that is a view of every other entry of a
    longer array (a band subset, ``sat[::2]``) is a valid input: the stored kernels,
    which take C-contiguous arrays only, refused it with a TypeError."""
    from mehs.synthesis import _native

    monkeypatch.setattr(_native, "_loaded", {})
    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path))          # the stored kernels
    rng = np.random.default_rng(3)
    nb, t = 5, np.array([1.0, 4.0])
    stack = [np.minimum(rng.poisson(300 * tj, (6, 7, nb)) + 32, 4095).astype(np.uint16)
             for tj in t]
    darks = [np.full((7, nb), 32.0, np.float32)] * 2
    sat2 = np.repeat(np.linspace(3000, 4000, nb).astype(np.float32), 2)
    cal2 = np.repeat(np.linspace(0.5, 2.0, nb).astype(np.float32), 2)
    strided = merge_bracket(stack, t, method=method, darks=darks, saturation=sat2[::2],
                            calibration=cal2[::2])
    packed = merge_bracket(stack, t, method=method, darks=darks,
                           saturation=np.ascontiguousarray(sat2[::2]),
                           calibration=np.ascontiguousarray(cal2[::2]))
    np.testing.assert_array_equal(np.asarray(strided.radiance), np.asarray(packed.radiance))
    np.testing.assert_array_equal(strided.chi2, packed.chi2)
    kind = "poisson_linear" if method == "poisson" else "debevec_linear"
    assert _native.is_stored(kind, np.uint16, 2)          # the stored kernel ran them
