"""Ghost detection against the simulator's truth (guards: mehs was right here).

The truth of a moved pixel is its non-centrality λ = Σ_bands Σ_j w_j (x_j − x̄_w)² under
the simulated sensor's true noise (w_j = t_j²/var_j over the samples below saturation):
the consistency test's ideal power is the non-central χ² tail above its α quantile
(scipy.stats.ncx2), independent of mehs. A pixel whose ideal power is > 0.999 must be
found; static pixels must be flagged at about α; the scene's ghost fraction must fail the
dataset rule when the truly moved fraction does.
"""

import numpy as np
import pytest
from scipy.stats import chi2 as chi2_dist, ncx2

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from mehs.cube import SpectralCube
from mehs.dataset.quality import judge
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.fuse import fuse_bracket
from mehs.synthesis.ghost import detect_ghosts


def _ideal_power(sim, sen, alpha):
    """float64 ``(lines, samples)`` ideal power of the pooled χ² test at each pixel."""
    g = sen.gain_dn_per_e
    sw = swx = swx2 = 0.0
    n_ok = 0
    for j, t in enumerate(sim.times_ms):
        x = sim.scene.radiance_at(j).astype(np.float64) * sim.truth_dn_per_ms   # DN/ms
        y = x * t
        var = g * y + g * g * (sen.read_noise_e ** 2 + sen.dark_current_e_per_ms * t) + 1 / 12
        z = sen.expected_dn(sim.scene.radiance_at(j), t, include_fpn=False,
                            wavelengths=sim.wavelengths)
        ok = z < 0.98 * 4095 - 3 * np.sqrt(var)
        w = ok * t * t / var
        sw, swx, swx2 = sw + w, swx + w * x, swx2 + w * x * x
        n_ok = n_ok + ok
    lam = np.where(sw > 0, swx2 - swx ** 2 / np.where(sw > 0, sw, 1.0), 0.0).sum(axis=2)
    dof = np.maximum(n_ok - 1, 0).sum(axis=2)
    d = np.maximum(dof, 1)
    return np.where(dof > 0, ncx2.sf(chi2_dist.isf(alpha, d), d, np.maximum(lam, 1e-12)), 0.0)


@pytest.mark.parametrize("kind,bands,times", [("lamp", 31, (0.5, 2.0, 8.0)),
                                              ("window", 3, (1.0, 4.0, 16.0, 64.0))])
def test_moved_pixels_are_found_as_the_ideal_test_finds_them(kind, bands, times):
    wl = (np.arange(400.0, 701.0, 10.0) if bands == 31 else np.array([460.0, 540.0, 610.0]))
    scene = make_scene(kind, lines=40, samples=40, wavelengths=wl, seed=1, motion=True,
                       fwhm=np.full(wl.size, 10.0 if bands == 31 else 60.0))
    sen = SensorModel(seed=1)
    sim = simulate_bracket(scene, sen, times, seed=1, white=False)
    br = Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks),
                 [None] * len(times), sim.times_ms, wl, bit_depth=12)
    r = fuse_bracket(br, response="linear", ghost_alpha=1e-4, check_response=False)
    raw = detect_ghosts(r.extras["chi2"], r.extras["dof"], alpha=1e-4, min_pixels=1, grow=0)
    moved = scene.moved_between(range(len(times)))
    power = _ideal_power(sim, sen, 1e-4)
    sure = moved & (power > 0.999)
    assert sure.sum() > 30
    assert raw.mask[sure].all(), int((sure & ~raw.mask).sum())
    # the expected number of hits over all moved pixels, within its binomial spread
    m = moved & (r.extras["dof"] > 0)
    exp, sd = power[m].sum(), np.sqrt((power[m] * (1 - power[m])).sum())
    assert abs(raw.mask[m].sum() - exp) <= 4 * sd + 3, (raw.mask[m].sum(), exp, sd)
    # static pixels: α before the clean-up (1e-4 of ~1500: 0 or 1), none after it
    static = ~moved & (r.extras["dof"] > 0)
    assert raw.mask[static].sum() <= 2
    final = (r.mask & 2) > 0
    assert not (final & ~moved & ~_grown(moved)).any()
    # the scene fails the dataset's ghost rule, as its truly moved fraction does
    assert moved.mean() > 0.01 and r.summary["ghost_fraction"] > 0.01
    assert 0.9 * moved.mean() <= r.summary["ghost_fraction"] <= 1.5 * moved.mean()
    status, reasons = judge({"ghost_fraction": r.summary["ghost_fraction"]})
    assert status == "fail" and any("ghost" in x for x in reasons)


def _grown(m):
    import cv2

    return cv2.dilate(m.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=1).astype(bool)


def test_a_static_scene_with_a_saturated_lamp_passes_the_ghost_rule():
    wl = SPECIM_IQ_WAVELENGTHS[::12].copy()
    scene = make_scene("lamp", lines=40, samples=40, wavelengths=wl, seed=2)
    sen = SensorModel(seed=2)
    sim = simulate_bracket(scene, sen, (2.0, 8.0, 32.0), seed=2, white=False)
    br = Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks), [None] * 3,
                 sim.times_ms, wl, bit_depth=12)
    r = fuse_bracket(br, response="linear", check_response=False)
    assert r.summary["saturated_fraction"] > 0.005        # the lamp clips in every exposure
    raw = detect_ghosts(r.extras["chi2"], r.extras["dof"], alpha=1e-2, min_pixels=1, grow=0)
    has = r.extras["dof"] > 0
    assert 0.003 <= raw.mask[has].mean() <= 0.02, raw.mask[has].mean()
    assert r.summary["ghost_fraction"] == 0.0
    status, reasons = judge({"ghost_fraction": r.summary["ghost_fraction"]})
    assert not any("ghost" in x for x in reasons)
