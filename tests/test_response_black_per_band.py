"""Per-band response curves near black, against the simulator's truth.

A per-band curve's scale is not fixed by its band's data (``f → s·f``, ``E → s·E``); the
gauge ``g(Z_mid) = ln Z_mid`` took it from the smoothness prior's extrapolation in a dark
band whose samples never reach ``Z_mid``. Under a sodium lamp the blue and red ends are
such bands, and they are the scene's darkest decile: its radiance was −100 % of the truth
(s-curve sensor: the band's table fell to −1e23 above its data, the constant then made
the curve flat) or +71 % (gamma sensor), and on a natural scene the direct solve was
singular. Bands are now tied to the shared curve over the levels they cover.
"""


import numpy as np
import pytest

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from _checks import bracket_of, decile_bias, true_curve
from mehs.synthesis.fuse_response import recover_response
from mehs.synthesis.response import weighting_table
from mehs.synthesis.response_offset import tie_bands_to_reference


def _bracket(kind, response, times=(1.0, 4.0, 16.0), size=72):
    wl = SPECIM_IQ_WAVELENGTHS[::24]
    if kind == "natural":
        from mehs.scenes.natural import make_natural_scene

        scene = make_natural_scene(size, size, wl, seed=1)
    else:
        scene = make_scene(kind, lines=size, samples=size, wavelengths=wl, seed=1)
    sensor = SensorModel(response=response, seed=3)
    sim = simulate_bracket(scene, sensor, list(times))
    br = bracket_of(sim, wl)
    return sim, br, sensor


@pytest.mark.parametrize("response", ["s-curve", "gamma"])
def test_dark_bands_of_a_per_band_curve_keep_their_scale(response):
    # before: darkest decile −100 % (s-curve), +71 % (gamma); the true curve +1 %, +5 %
    sim, br, _ = _bracket("lamp", response)
    curve = recover_response(br, shared=False)
    bias = decile_bias(br, sim, curve)
    assert np.abs(bias).max() < 0.12 and np.ptp(bias) < 0.12, np.round(bias, 3)


def test_per_band_curve_of_a_natural_scene_follows_the_true_curve():
    # before: "the response system with the dark offset is singular" (direct solve),
    # darkest deciles −100 % and +1.5e6 % with the rounds
    sim, br, sensor = _bracket("natural", "s-curve")
    curve = recover_response(br, shared=False)
    excess = decile_bias(br, sim, curve) - decile_bias(br, sim, true_curve(sensor))
    assert np.abs(excess).max() < 0.07, np.round(excess, 3)


def test_tie_puts_each_band_on_the_reference_over_its_own_levels():
    L = 256
    lev = np.arange(L)
    F = (lev + 5.0) ** 1.25                       # the reference, linear domain, > 0
    rng = np.random.default_rng(0)
    # band 0 sees levels 20..60 only, band 1 20..250; each its own scale and constant,
    # and a table that falls away above its data (the prior's extrapolation)
    Z = np.stack([rng.integers(20, 61, (400, 2)), rng.integers(20, 251, (400, 2))], axis=2)
    D = np.full(Z.shape, 15.0)
    f = np.stack([3.0 * F - 40.0, 0.5 * F + 7.0])
    f[0, 61:] = -1e23
    g, stats = tie_bands_to_reference(f, np.log(F), Z, D, weighting_table("hat", L))
    assert stats["bands_from_reference"] == 0
    np.testing.assert_allclose(g[:, 15:251], np.tile(np.log(F)[15:251], (2, 1)), atol=1e-9)
    # outside the band's levels it follows the reference's shape, continuously
    np.testing.assert_allclose(g[0, 61:], np.log(F[61:]), atol=1e-9)
    assert np.all(np.isfinite(g)) and np.all(np.diff(g, axis=1) > 0)
