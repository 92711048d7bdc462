"""De-ghosting against the simulator's truth at the reference exposure's instant.

``ghosts="deghost"`` must give the radiance the reference exposure saw. Where the
reference is saturated inside the moving area, a shorter exposure saw another instant:
its value is used only when it is consistent with the reference's saturated sample
(radiance ≥ its bound); otherwise the pixel is flagged (mask bit 1, a lower bound), as
the merge flags a band saturated in every exposure, never invented.
"""

import numpy as np
import pytest

from mehs.capture.scene import SPECIM_IQ_WAVELENGTHS, make_scene
from mehs.capture.sensor import SensorModel
from mehs.capture.simulate import simulate_bracket
from mehs.cube import SpectralCube
from mehs.synthesis.bracket import Bracket
from mehs.synthesis.fuse import fuse_bracket
from mehs.synthesis.merge import MASK_GHOST, MASK_SATURATED


def _moving(n=32, bands=8, t0=4.0, seed=1):
    """A chart with the simulator's bright cloud (3 × the white, D65) drifting right; ×4 bracket."""
    wl = SPECIM_IQ_WAVELENGTHS[::204 // bands][:bands].copy()
    scene = make_scene("colorchecker", lines=n, samples=n, wavelengths=wl, seed=seed,
                       motion=True)
    sen = SensorModel(seed=seed)
    sim = simulate_bracket(scene, sen, t0 * 4.0 ** np.arange(3), seed=seed, white=False)
    br = Bracket([SpectralCube(e, wl) for e in sim.exposures], list(sim.darks), [None] * 3,
                 sim.times_ms, wl, bit_depth=12)
    return sim, sen, br


def _truth_at(sim, sen, j):
    """DN/ms the reference exposure ``j`` saw, and its noise σ (DN/ms), from the simulator."""
    t = sim.times_ms[j]
    x = sim.scene.radiance_at(j).astype(np.float64) * sim.truth_dn_per_ms
    g = sen.gain_dn_per_e
    var = g * x * t + g * g * (sen.read_noise_e ** 2 + sen.dark_current_e_per_ms * t) + 1 / 12
    return x, np.sqrt(var) / t


def test_a_reference_saturated_in_the_moving_area_is_flagged_not_invented():
    """Reference = the longest exposure, where the cloud saturates: its samples fell back
    to the shorter exposures, which saw the cloud elsewhere — 94 % of them > 5σ from the
    reference's radiance (0.04×–2.5×), none flagged."""
    sim, sen, br = _moving()
    r = fuse_bracket(br, response="linear", ghosts="deghost", reference=2, check_response=False)
    assert r.summary["ghost_reference_exposure"] == 2
    truth, sig = _truth_at(sim, sen, 2)
    est = r.radiance.data.astype(np.float64)
    ghost = (r.mask & MASK_GHOST) > 0
    flagged = (r.mask & MASK_SATURATED) > 0
    sat_ref = np.asarray(sim.exposures[2]) >= 0.98 * 4095
    in_region = ghost[..., None] & sat_ref
    assert in_region.sum() > 40                      # the test has something to check
    off = np.abs(est - truth) > 5 * sig
    # every sample off the truth is a flagged lower bound, never above the truth
    bad = in_region & off & ~(flagged[..., None] & (est <= truth + 5 * sig))
    assert bad.sum() == 0, (bad.sum(), in_region.sum())
    assert flagged[ghost].any()
    # what is written unflagged agrees with what the reference saw
    ok = in_region & ~flagged[..., None]
    assert np.all(np.abs(est - truth)[ok] <= 5 * sig[ok])
    # the summary's saturated fraction counts the flagged pixels
    assert r.summary["saturated_fraction"] == pytest.approx(float(flagged.mean()))
    assert r.summary["ghost_reference_saturated_fraction"] > 0


def test_deghosted_pixels_match_the_reference_instant_and_the_seam_is_clean():
    """Guard (mehs was right here): with an unsaturated reference the moved pixels carry
    the reference instant's radiance within its noise, and the pixels just outside the
    mask (merged from every exposure) agree with it too — no seam."""
    import cv2

    sim, sen, br = _moving(t0=0.5)
    r = fuse_bracket(br, response="linear", ghosts="deghost", check_response=False)
    ref = r.summary["ghost_reference_exposure"]
    truth, sig = _truth_at(sim, sen, ref)
    z = (r.radiance.data.astype(np.float64) - truth) / sig
    ghost = (r.mask & MASK_GHOST) > 0
    assert ghost.sum() > 20
    assert not ((r.mask & MASK_SATURATED) > 0)[ghost].any()
    assert np.percentile(np.abs(z[ghost]), 99) < 3.5
    ring = cv2.dilate(ghost.astype(np.uint8), np.ones((3, 3), np.uint8),
                      iterations=2).astype(bool) & ~ghost
    assert np.percentile(np.abs(z[ring]), 99) < 3.5 and np.abs(z[ring]).max() < 6
    assert r.summary["ghost_reference_saturated_fraction"] == 0.0
